"""Blender's world as Tessera's `--env` flags.

glTF carries no world, so the add-on maps it: an Environment Texture (an .hdr or .exr image)
feeding a Background node becomes `--env FILE` with its strength and its turn about Blender's Z
axis (glTF's +Y); a plain colour becomes `--env R,G,B`. Anything else is listed, never dropped
silently.
"""

import math
import os
import tempfile

# Blender's equirectangular maps centre on +X; Tessera's (as Mitsuba's) on +Z of glTF, which is
# Blender's -Y. Both run the same way round the vertical, so the map is turned a quarter turn,
# less the Mapping node's own turn about Z.
QUARTER_TURN_DEGREES = 90.0

MAP_EXTENSIONS = (".hdr", ".exr")


class WorldMapping:
    """The flags for `tessera submit`, and what could not be mapped (each a sentence)."""

    def __init__(self):
        self.flags = []
        self.unmapped = []

    def __repr__(self):
        return f"WorldMapping(flags={self.flags!r}, unmapped={self.unmapped!r})"


def _number(value):
    return f"{value:.6g}"


def _active_output(tree):
    outputs = [n for n in tree.nodes if n.type == "OUTPUT_WORLD"]
    for node in outputs:
        if node.is_active_output:
            return node
    return outputs[0] if outputs else None


def _source(socket):
    """The node feeding `socket`, or None."""
    if not socket.is_linked:
        return None
    return socket.links[0].from_node


def _image_file(image, unmapped):
    """A path Tessera can read for `image`: its file, or a packed copy written out."""
    name = image.name
    if image.packed_file is not None:
        ext = os.path.splitext(image.filepath_raw or name)[1].lower() or ".hdr"
        path = os.path.join(tempfile.mkdtemp(prefix="tessera-world-"), "world" + ext)
        with open(path, "wb") as f:
            f.write(image.packed_file.data)
    else:
        import bpy

        path = bpy.path.abspath(image.filepath, library=image.library)
    if os.path.splitext(path)[1].lower() not in MAP_EXTENSIONS:
        unmapped.append(f"environment image '{name}' is not an .hdr or .exr file (Tessera reads those)")
        return None
    if not os.path.isfile(path):
        unmapped.append(f"environment image '{name}' is missing: {path}")
        return None
    return path


def _turn(mapping, unmapped):
    """Degrees the Mapping node `mapping` turns the map about Z (Blender's up)."""
    if mapping is None:
        return 0.0
    if mapping.vector_type not in ("POINT", "TEXTURE"):
        unmapped.append(f"Mapping node '{mapping.name}' of type {mapping.vector_type} (only Point and Texture are mapped)")
        return 0.0
    inputs = mapping.inputs
    for socket in ("Location", "Rotation", "Scale"):
        if socket in inputs and inputs[socket].is_linked:
            unmapped.append(f"Mapping node '{mapping.name}': a linked {socket} (only constant values are mapped)")
    rx, ry, rz = inputs["Rotation"].default_value
    if abs(rx) > 1e-6 or abs(ry) > 1e-6:
        unmapped.append(f"Mapping node '{mapping.name}': a turn about X or Y (only the turn about Z is mapped)")
    if any(abs(v) > 1e-6 for v in inputs["Location"].default_value) or any(
        abs(v - 1.0) > 1e-6 for v in inputs["Scale"].default_value
    ):
        unmapped.append(f"Mapping node '{mapping.name}': a location or scale (only the turn about Z is mapped)")
    degrees = math.degrees(rz)
    # A Point mapping turns the lookup direction; a Texture mapping turns the other way.
    return degrees if mapping.vector_type == "POINT" else -degrees


def _uses_nodes(world):
    """Worlds always use their node tree from Blender 5 (`use_nodes` is going away)."""
    import bpy

    return bpy.app.version >= (5, 0, 0) or world.use_nodes


def map_world(world):
    """The `--env` flags for Blender world `world` (None: no world, a black one)."""
    m = WorldMapping()
    if world is None:
        m.flags = ["--env", "0"]
        return m
    if world.node_tree is None or not _uses_nodes(world):
        r, g, b = world.color[:3]
        m.flags = ["--env", ",".join(_number(c) for c in (r, g, b))]
        return m
    output = _active_output(world.node_tree)
    if output is None:
        m.flags = ["--env", "0"]
        return m
    if output.inputs.get("Volume") is not None and output.inputs["Volume"].is_linked:
        m.unmapped.append("a world volume (Tessera renders no volumes in the world)")
    background = _source(output.inputs["Surface"])
    if background is None:
        m.flags = ["--env", "0"]
        return m
    if background.type != "BACKGROUND":
        m.unmapped.append(f"world shader '{background.name}' ({background.bl_label}): only a Background node is mapped")
        return m
    strength_socket = background.inputs["Strength"]
    if strength_socket.is_linked:
        m.unmapped.append(f"the Background's Strength comes from a node (only a constant is mapped); 1 used")
        strength = 1.0
    else:
        strength = strength_socket.default_value
    colour = background.inputs["Color"]
    texture = _source(colour)
    if texture is None:
        r, g, b = colour.default_value[:3]
        m.flags = ["--env", ",".join(_number(c * strength) for c in (r, g, b))]
        return m
    if texture.type != "TEX_ENVIRONMENT":
        m.unmapped.append(f"world colour from '{texture.name}' ({texture.bl_label}): only an Environment Texture is mapped")
        return m
    if texture.image is None:
        m.unmapped.append(f"Environment Texture '{texture.name}' has no image")
        return m
    if texture.projection != "EQUIRECTANGULAR":
        m.unmapped.append(f"Environment Texture '{texture.name}' in {texture.projection} projection (only equirectangular is mapped)")
        return m
    path = _image_file(texture.image, m.unmapped)
    if path is None:
        return m
    mapping = _source(texture.inputs["Vector"])
    if mapping is not None and mapping.type != "MAPPING":
        if mapping.type != "TEX_COORD":
            m.unmapped.append(f"the map's coordinates come from '{mapping.name}' ({mapping.bl_label}): only a Mapping node is mapped")
        mapping = None
    if mapping is not None:
        feeding = _source(mapping.inputs["Vector"])
        if feeding is not None and feeding.type != "TEX_COORD":
            m.unmapped.append(f"the Mapping node's vector comes from '{feeding.name}' ({feeding.bl_label})")
    rotate = (QUARTER_TURN_DEGREES - _turn(mapping, m.unmapped)) % 360.0
    if strength <= 0.0:
        m.flags = ["--env", "0"]
        return m
    m.flags = ["--env", path, "--env-strength", _number(strength), "--env-rotate", _number(rotate)]
    return m
