"""Builds the installable add-on: python3 integrations/blender/build_zip.py [OUT.zip]

The zip holds the `tessera` package folder, as Blender's Preferences > Add-ons > Install from
Disk expects. Default output: integrations/blender/dist/tessera-blender.zip.
"""

import os
import sys
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))


def build(out):
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    package = os.path.join(HERE, "tessera")
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for name in sorted(os.listdir(package)):
            if name.endswith(".py"):
                z.write(os.path.join(package, name), os.path.join("tessera", name))
    return out


if __name__ == "__main__":
    print(build(sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "dist", "tessera-blender.zip")))
