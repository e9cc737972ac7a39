"""Tessera render farm: submit the scene from Blender, follow it, bring the frames back.

The scene is exported to a temporary .glb with Blender's own glTF exporter, the world mapped to
`--env` (see `world.py`), and handed to `tessera submit --detach`; a timer polls the render
without blocking the interface and downloads the frames to the scene's output path when it
ends. Scripts call `bpy.ops.tessera.submit(wait=True)`, which returns once every frame is written.
"""

bl_info = {
    "name": "Tessera render farm",
    "author": "Tessera",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "Properties > Render > Tessera",
    "description": "Submit the scene to a Tessera render farm and bring the frames back",
    "category": "Render",
}

import os
import shlex
import shutil
import tempfile
import threading
import time

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import farm as farm_mod
from . import world as world_mod

# Seconds between two looks at a render that is being followed.
POLL_SECONDS = 1.0


def _preferences():
    addon = bpy.context.preferences.addons.get(__package__)
    return addon.preferences if addon else None


def _farm():
    prefs = _preferences()
    return farm_mod.Farm(
        coordinator=prefs.coordinator if prefs else "",
        token=prefs.token if prefs else "",
        binary=bpy.path.abspath(prefs.binary) if prefs and prefs.binary else "",
    )


class TesseraPreferences(bpy.types.AddonPreferences):
    """Kept in Blender's preferences, never in the .blend (a token would travel with it)."""

    bl_idname = __package__

    coordinator: StringProperty(
        name="Coordinator",
        description="The farm's coordinator, e.g. http://farm.example:7878 (empty: TESSERA_COORDINATOR)",
    )
    token: StringProperty(
        name="Token",
        description="Your token for the farm (empty: TESSERA_TOKEN)",
        subtype="PASSWORD",
    )
    binary: StringProperty(
        name="tessera command",
        description="Path to the tessera binary (empty: found on PATH)",
        subtype="FILE_PATH",
    )
    dashboard: StringProperty(
        name="Dashboard",
        description="The farm's dashboard, e.g. http://farm.example:8080 (for the panel's link)",
    )

    def draw(self, context):
        layout = self.layout
        for name in ("coordinator", "token", "binary", "dashboard"):
            layout.prop(self, name)


class TesseraSettings(bpy.types.PropertyGroup):
    """What to render, stored with the scene."""

    quality: EnumProperty(
        name="Quality",
        items=[
            ("SAMPLES", "Samples", "Every pixel gets the same number of samples"),
            ("ERROR", "Target error", "Adaptive: each tile stops once its noise is below the target"),
        ],
        default="SAMPLES",
    )
    samples: IntProperty(
        name="Samples",
        description="Samples per pixel (0: the scene's Cycles sample count)",
        default=0,
        min=0,
        max=1 << 20,
    )
    target_error: FloatProperty(
        name="Target error", description="Relative noise to reach per tile", default=0.01, min=0.0005, max=1.0
    )
    use_scene_frames: BoolProperty(name="Scene's frame range", default=True)
    frame_start: IntProperty(name="Start", default=1, min=0)
    frame_end: IntProperty(name="End", default=1, min=0)
    camera: StringProperty(name="Camera", description="Camera object to render from (empty: the active camera)")
    output: StringProperty(
        name="Output",
        description="Where frames are written, # for the frame number (empty: the scene's output path)",
        subtype="FILE_PATH",
    )
    variant: StringProperty(name="Variant", description="A material variant (KHR_materials_variants), if any")
    selected_collection: BoolProperty(
        name="Active collection only", description="Export the active collection instead of the visible scene"
    )
    # What the panel shows of the render being followed.
    render_id: StringProperty(name="Render")
    status: StringProperty(name="Status")
    progress: FloatProperty(name="Progress", min=0.0, max=1.0, subtype="FACTOR")
    last_submit: StringProperty(name="Last command", description="The submit command last run (without the token)")


def _frames(scene, settings):
    if settings.use_scene_frames:
        return scene.frame_start, scene.frame_end, max(1, scene.frame_step)
    return settings.frame_start, max(settings.frame_start, settings.frame_end), 1


def _output(scene, settings):
    path = settings.output or scene.render.filepath or "//render/####"
    return bpy.path.abspath(path)


def _samples(scene, settings):
    if settings.samples > 0:
        return settings.samples
    cycles = getattr(scene, "cycles", None)
    return int(getattr(cycles, "samples", 0) or 64)


def _moves():
    """True when something in the file is animated (an action: objects, armatures, shape keys)."""
    return len(bpy.data.actions) > 0


def _export(context, settings, animated, directory):
    """The scene as a .glb in `directory`: cameras, lights (the exporter's standard unit
    conversion), and the animation over the frames rendered. A still of an animated scene takes
    its animation too, so that it is posed at its frame as Blender shows it (a skinned figure
    would otherwise stand in its rest pose): `submit_flags` then names the frame."""
    animated = animated or _moves()
    path = os.path.join(directory, (bpy.path.display_name_from_filepath(bpy.data.filepath) or "scene") + ".glb")
    scene = context.scene
    # The exporter samples the animation over the scene's frame range and poses a still at the
    # current frame: both are set for the export, and given back after it.
    kept = scene.frame_start, scene.frame_end, scene.frame_current
    start, end, _ = _frames(scene, settings)
    try:
        if animated:
            scene.frame_start, scene.frame_end = start, max(start, end)
        scene.frame_set(start)
        _run_exporter(path, settings, animated)
    finally:
        scene.frame_start, scene.frame_end = kept[0], kept[1]
        scene.frame_set(kept[2])
    return path


def _run_exporter(path, settings, animated):
    bpy.ops.export_scene.gltf(
        filepath=path,
        export_format="GLB",
        use_visible=not settings.selected_collection,
        use_active_collection=settings.selected_collection,
        export_cameras=True,
        export_lights=True,
        export_import_convert_lighting_mode="SPEC",
        export_apply=True,
        export_animations=animated,
        export_frame_range=animated,
        export_yup=True,
    )


def _camera_name(scene, settings):
    ob = scene.objects.get(settings.camera) if settings.camera else scene.camera
    if ob is None or ob.type != "CAMERA":
        return None
    # The exporter names a glTF camera after the camera's data block.
    return ob.data.name


def submit_flags(context, settings, env):
    """The `tessera submit` flags for the scene (with `env`, the world's flags)."""
    scene = context.scene
    r = scene.render
    scale = r.resolution_percentage / 100.0
    flags = ["--width", str(max(1, int(r.resolution_x * scale))), "--height", str(max(1, int(r.resolution_y * scale)))]
    if settings.quality == "SAMPLES":
        flags += ["--spp", str(_samples(scene, settings)), "--target-error", "0"]
    else:
        flags += ["--spp", str(max(_samples(scene, settings), 16)), "--target-error", f"{settings.target_error:g}"]
    start, end, step = _frames(scene, settings)
    fps = r.fps / (r.fps_base or 1.0)
    flags += ["--fps", f"{fps:.6g}"]
    if end > start:
        flags += ["--frames", f"{start}-{end}" + (f"x{step}" if step > 1 else "")]
    elif _moves():
        flags += ["--frame", str(start)]
    camera = _camera_name(scene, settings)
    if camera:
        flags += ["--camera", camera]
    if r.film_transparent:
        flags.append("--transparent")
    if settings.variant:
        flags += ["--variant", settings.variant]
    name = bpy.path.display_name_from_filepath(bpy.data.filepath) or scene.name
    flags += ["--name", name]
    return flags + list(env)


class _Follow:
    """A render being followed on a thread of its own: the timer reads what it found."""

    def __init__(self, farm, render, out, frames):
        self.farm, self.render, self.out = farm, render, out
        # A sequence's frames not downloaded yet: each is fetched as it finishes.
        self.frames, self.pending = frames, set(frames)
        self.since = time.time()
        self.status_line, self.fraction = "submitted", 0.0
        self.done, self.error = False, None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _fetch_finished(self, status):
        """Downloads the sequence's frames finished since the last look."""
        done = (status.get("frames") or {}).get("done", 0)
        if len(self.frames) - len(self.pending) >= done:
            return
        self.farm.fetch(self.render, self.out, sorted(self.pending))
        for f in list(self.pending):
            path = farm_mod.frame_pattern(self.out, f)
            if os.path.isfile(path) and os.path.getmtime(path) >= self.since - 1:
                self.pending.discard(f)

    def _run(self):
        try:
            while not self.stop.is_set():
                status = self.farm.status(self.render)
                self.fraction, self.status_line = farm_mod.progress(status)
                state = status.get("state")
                if self.render.startswith("s"):
                    self._fetch_finished(status)
                if state == "done":
                    target = farm_mod.frame_pattern(self.out, self.frames[0])
                    if not self.render.startswith("s"):
                        self.farm.fetch(self.render, target)
                    self.status_line = f"done: written to {os.path.dirname(target)}"
                    break
                if state in ("failed", "cancelled"):
                    raise farm_mod.FarmError(f"render {self.render} {state}" + (f": {status['message']}" if status.get("message") else ""))
                self.stop.wait(POLL_SECONDS)
        except farm_mod.FarmError as e:
            self.error = str(e)
        except Exception as e:  # a status the add-on did not expect: said, not raised in Blender
            self.error = f"following render {self.render} failed: {e}"
        self.done = True


_following = {}

# The folder of the last export: kept (its .glb re-renders locally as the farm rendered it, the
# command being the panel's last one) until the next submit.
_last_export = None


def _fresh_export_folder():
    global _last_export
    if _last_export and os.path.isdir(_last_export):
        shutil.rmtree(_last_export, ignore_errors=True)
    _last_export = tempfile.mkdtemp(prefix="tessera-blender-")
    return _last_export


def _tick():
    """The timer: copies what the follower threads found into the panel."""
    for scene_name, follow in list(_following.items()):
        scene = bpy.data.scenes.get(scene_name)
        if scene is not None:
            s = scene.tessera
            s.progress = follow.fraction
            s.status = follow.error or follow.status_line
        if follow.done:
            del _following[scene_name]
    for window in bpy.context.window_manager.windows if bpy.context.window_manager else []:
        for area in window.screen.areas:
            if area.type == "PROPERTIES":
                area.tag_redraw()
    return POLL_SECONDS if _following else None


class TESSERA_OT_submit(bpy.types.Operator):
    """Export the scene, submit it to the Tessera farm and bring the frames back"""

    bl_idname = "tessera.submit"
    bl_label = "Submit to Tessera"
    bl_options = {"REGISTER"}

    wait: BoolProperty(name="Wait", description="Block until every frame is written (for scripts)", default=False)

    def execute(self, context):
        scene = context.scene
        settings = scene.tessera
        try:
            farm = _farm()
            mapping = world_mod.map_world(scene.world)
            if mapping.unmapped:
                # Listed before anything is sent: the farm renders without them.
                self.report({"WARNING"}, "Not mapped to Tessera: " + "; ".join(mapping.unmapped))
            start, end, step = _frames(scene, settings)
            animated = end > start
            directory = _fresh_export_folder()
            glb = _export(context, settings, animated, directory)
            flags = submit_flags(context, settings, mapping.flags)
            settings.last_submit = shlex.join(["tessera", "submit", glb, "--detach"] + flags)
            render = farm.submit(glb, flags)
        except farm_mod.FarmError as e:
            settings.status = f"not submitted: {e}"
            self.report({"ERROR"}, f"Tessera: {e}")
            return {"CANCELLED"}
        settings.render_id = render
        settings.status = f"render {render} submitted"
        settings.progress = 0.0
        out = _output(scene, settings)
        follow = _Follow(farm, render, farm_mod.frame_pattern(out), list(range(start, end + 1, step)))
        if self.wait:
            follow.thread.join()
            settings.progress = follow.fraction
            settings.status = follow.error or follow.status_line
            if follow.error:
                self.report({"ERROR"}, f"Tessera: {follow.error}")
                return {"CANCELLED"}
            self.report({"INFO"}, f"Tessera: render {render} {follow.status_line}")
            return {"FINISHED"}
        old = _following.pop(scene.name, None)
        if old is not None:
            old.stop.set()
        _following[scene.name] = follow
        if not bpy.app.timers.is_registered(_tick):
            bpy.app.timers.register(_tick, first_interval=POLL_SECONDS)
        self.report({"INFO"}, f"Tessera: render {render} submitted")
        return {"FINISHED"}


class TESSERA_OT_cancel(bpy.types.Operator):
    """Cancel the render this scene last submitted"""

    bl_idname = "tessera.cancel"
    bl_label = "Cancel render"

    @classmethod
    def poll(cls, context):
        return bool(context.scene.tessera.render_id)

    def execute(self, context):
        settings = context.scene.tessera
        try:
            _farm().cancel(settings.render_id)
        except farm_mod.FarmError as e:
            self.report({"ERROR"}, f"Tessera: {e}")
            return {"CANCELLED"}
        follow = _following.get(context.scene.name)
        if follow is not None:
            follow.stop.set()
        settings.status = f"render {settings.render_id} cancelled"
        return {"FINISHED"}


class TESSERA_OT_dashboard(bpy.types.Operator):
    """Open the farm's dashboard on this render"""

    bl_idname = "tessera.dashboard"
    bl_label = "Open dashboard"

    @classmethod
    def poll(cls, context):
        prefs = _preferences()
        return bool(prefs and prefs.dashboard)

    def execute(self, context):
        url = _preferences().dashboard.rstrip("/") + "/"
        if context.scene.tessera.render_id:
            url += "#/render/" + context.scene.tessera.render_id
        bpy.ops.wm.url_open(url=url)
        return {"FINISHED"}


class TESSERA_PT_panel(bpy.types.Panel):
    bl_label = "Tessera"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.tessera
        prefs = _preferences()
        where = (prefs.coordinator if prefs and prefs.coordinator else os.environ.get("TESSERA_COORDINATOR", ""))
        layout.label(text=f"Farm: {where or 'not set (add-on preferences)'}")
        layout.prop(settings, "quality")
        if settings.quality == "SAMPLES":
            layout.prop(settings, "samples")
        else:
            layout.prop(settings, "target_error")
            layout.prop(settings, "samples", text="At most")
        layout.prop(settings, "use_scene_frames")
        if not settings.use_scene_frames:
            row = layout.row()
            row.prop(settings, "frame_start")
            row.prop(settings, "frame_end")
        layout.prop_search(settings, "camera", context.scene, "objects")
        layout.prop(settings, "output")
        layout.prop(context.scene.render, "film_transparent", text="Transparent film")
        layout.prop(settings, "variant")
        layout.prop(settings, "selected_collection")
        layout.operator(TESSERA_OT_submit.bl_idname, icon="RENDER_ANIMATION")
        if settings.render_id:
            box = layout.box()
            box.label(text=f"Render {settings.render_id}: {settings.status}")
            box.prop(settings, "progress", text="")
            row = box.row()
            row.operator(TESSERA_OT_cancel.bl_idname, icon="CANCEL")
            row.operator(TESSERA_OT_dashboard.bl_idname, icon="URL")


CLASSES = (TesseraPreferences, TesseraSettings, TESSERA_OT_submit, TESSERA_OT_cancel, TESSERA_OT_dashboard, TESSERA_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.tessera = PointerProperty(type=TesseraSettings)


def unregister():
    for follow in _following.values():
        follow.stop.set()
    _following.clear()
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    del bpy.types.Scene.tessera
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
