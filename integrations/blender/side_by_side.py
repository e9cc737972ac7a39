"""Khronos assets side by side: Cycles and Tessera, the same scene through Blender.

    python3 integrations/blender/side_by_side.py --tessera target/release/tessera \
        --scenes ../shared/scenes --out docs/cycles

Each asset is imported with Blender's own glTF importer, framed by a camera added here and put
under a world: a constant white one, and an HDR map (../shared/environments). Cycles renders it
(CPU, a box filter one pixel wide, no denoising, adaptive sampling, clamping or glossy
filtering, 16 bounces); the add-on exports the same Blender scene to .glb and maps the world,
and `tessera render` renders it at the same size and samples. `tessera compare --covered` gives each renderer's mean over the
object's pixels (the background left out) and a picture of the difference. Prints one Markdown
table row per asset and world, and writes the pictures to --out.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile

import bpy  # noqa: E402  (first: it makes Blender's own modules importable)
from mathutils import Vector  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import tessera as addon  # noqa: E402

ASSETS = [
    "BoxTextured/glTF-Binary/BoxTextured.glb",
    "Duck/glTF-Binary/Duck.glb",
    "Suzanne/glTF/Suzanne.gltf",
    "WaterBottle/glTF/WaterBottle.gltf",
    "CesiumMan/glTF-Binary/CesiumMan.glb",
    "MetalRoughSpheresNoTextures/glTF-Binary/MetalRoughSpheresNoTextures.glb",
    "GlassHurricaneCandleHolder/glTF-Binary/GlassHurricaneCandleHolder.glb",
    "GlassVaseFlowers/glTF-Binary/GlassVaseFlowers.glb",
]


def frame(scene, size):
    """A camera looking at every mesh from the front, a little above, the whole in view."""
    corners = [o.matrix_world @ Vector(c) for o in scene.objects if o.type == "MESH" for c in o.bound_box]
    lo = Vector([min(c[k] for c in corners) for k in range(3)])
    hi = Vector([max(c[k] for c in corners) for k in range(3)])
    centre, radius = (lo + hi) / 2, (hi - lo).length / 2
    data = bpy.data.cameras.new("Front")
    data.angle = math.radians(40)
    cam = bpy.data.objects.new("Front", data)
    scene.collection.objects.link(cam)
    direction = Vector((0.35, -1.0, 0.3)).normalized()
    cam.location = centre + direction * (radius / math.sin(data.angle / 2) * 1.05)
    cam.rotation_euler = (-direction).to_track_quat("-Z", "Y").to_euler()
    data.clip_start, data.clip_end = radius * 0.01, radius * 100
    scene.camera = cam
    scene.render.resolution_x = scene.render.resolution_y = size


def world(scene, environment):
    w = bpy.data.worlds.new("World")
    if bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    nodes = w.node_tree.nodes
    background = nodes["Background"]
    if environment:
        texture = nodes.new("ShaderNodeTexEnvironment")
        texture.image = bpy.data.images.load(environment)
        texture.interpolation = "Closest"  # as Tessera looks maps up
        w.node_tree.links.new(texture.outputs["Color"], background.inputs["Color"])
    else:
        background.inputs["Color"].default_value = (1, 1, 1, 1)
    background.inputs["Strength"].default_value = 1.0
    scene.world = w


def cycles(scene, spp, exr, png):
    c = scene.cycles
    c.device, c.samples, c.use_denoising, c.use_adaptive_sampling = "CPU", spp, False, False
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    # Cycles blurs glossy and glass lobes after a rough bounce by default (Filter Glossy 1.0):
    # it darkened what is seen through glass by a quarter (docs/cycles.md). Off: the true image.
    c.blur_glossy = 0.0
    c.pixel_filter_type, c.filter_width = "BOX", 1.0
    c.max_bounces = c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = 16
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = True
    settings = scene.render.image_settings
    settings.file_format, settings.color_depth, settings.color_mode = "OPEN_EXR", "32", "RGBA"
    scene.render.filepath = exr
    bpy.ops.render.render(write_still=True)
    settings.file_format, settings.color_depth = "PNG", "8"
    bpy.data.images["Render Result"].save_render(png)


def tessera(context, binary, spp, out):
    settings = context.scene.tessera
    settings.quality, settings.samples, settings.use_scene_frames = "SAMPLES", spp, True
    context.scene.frame_start = context.scene.frame_end = 1
    mapping = addon.world.map_world(context.scene.world)
    glb = addon._export(context, settings, False, tempfile.mkdtemp(prefix="tessera-side-"))
    flags = addon.submit_flags(context, settings, mapping.flags)
    at = flags.index("--name")
    flags = flags[:at] + flags[at + 2:]
    done = subprocess.run([binary, "render", glb] + flags + ["--out", out, "-q"], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr)
    return mapping.unmapped


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--tessera", required=True)
    parser.add_argument("--scenes", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--assets", nargs="*", default=ASSETS)
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    environments = [("white", None), ("map", os.path.join(args.scenes, "..", "environments", "studio_small_03_1k.hdr"))]
    addon.register()
    print("| asset | world | pixels | Tessera mean R G B | Cycles mean R G B | difference |")
    print("|---|---|---:|---|---|---|")
    for asset in args.assets:
        for env_name, env in environments:
            bpy.ops.wm.read_factory_settings(use_empty=True)
            bpy.ops.import_scene.gltf(filepath=os.path.join(args.scenes, asset))
            scene = bpy.context.scene
            scene.render.engine = "CYCLES"
            for o in [o for o in scene.objects if o.type == "CAMERA"]:
                bpy.data.objects.remove(o)
            frame(scene, args.size)
            world(scene, env)
            stem = os.path.join(args.out, os.path.basename(asset).split(".")[0] + "-" + env_name)
            cycles(scene, args.spp, stem + "-cycles.exr", stem + "-cycles.png")
            tessera(bpy.context, os.path.abspath(args.tessera), args.spp, stem + "-tessera.exr")
            done = subprocess.run(
                [args.tessera, "compare", stem + "-tessera.exr", stem + "-cycles.exr", "--covered", "--json",
                 "--diff", stem + "-diff.png"],
                capture_output=True, text=True,
            )
            c = json.loads(done.stdout)
            a, b = c["mean"]["image"], c["mean"]["reference"]
            diff = " ".join(f"{100 * (x / y - 1):+.1f} %" if y > 0 else "-" for x, y in zip(a, b))
            rgb = lambda m: " ".join(f"{v:.4f}" for v in m)  # noqa: E731
            print(f"| {asset.split('/')[0]} | {env_name} | {c['pixels_compared']} | {rgb(a)} | {rgb(b)} | {diff} |", flush=True)
            for suffix in ("-cycles.exr", "-tessera.exr"):
                os.remove(stem + suffix)


if __name__ == "__main__":
    main()
