"""Talking to the farm through the `tessera` command: submit, status, fetch, cancel.

Nothing here imports Blender: the operator in `__init__.py` gathers the scene's settings and
hands them over. Every failure is a `FarmError` whose message is the command's own first line
of explanation, fit to show in Blender's status bar.
"""

import json
import os
import shutil
import subprocess

# Seconds a single command may take before the add-on gives up on it (a submit uploads the
# scene, so it gets longer).
COMMAND_SECONDS = 60
SUBMIT_SECONDS = 600


class FarmError(Exception):
    """A command failed; the message says why and what to do."""


class Farm:
    """A coordinator, the token for it, and the `tessera` binary that talks to it."""

    def __init__(self, coordinator="", token="", binary=""):
        self.coordinator = coordinator or os.environ.get("TESSERA_COORDINATOR", "")
        self.token = token or os.environ.get("TESSERA_TOKEN", "")
        self.binary = binary or shutil.which("tessera") or ""
        if not self.binary:
            raise FarmError(
                "the tessera command was not found: set its path in the add-on's preferences, or put it on PATH"
            )
        if not os.path.isfile(self.binary):
            raise FarmError(f"the tessera command '{self.binary}' does not exist: check the add-on's preferences")
        if not self.coordinator:
            raise FarmError(
                "no coordinator: set its URL in the add-on's preferences or in TESSERA_COORDINATOR "
                "(for example http://farm.example:7878)"
            )

    def _run(self, args, seconds=COMMAND_SECONDS):
        env = dict(os.environ)
        # The token travels in the environment, never on a command line others can read.
        env.pop("TESSERA_TOKEN", None)
        if self.token:
            env["TESSERA_TOKEN"] = self.token
        env["TESSERA_COORDINATOR"] = self.coordinator
        env["NO_COLOR"] = "1"
        try:
            done = subprocess.run(
                [self.binary] + list(args), env=env, capture_output=True, text=True, timeout=seconds
            )
        except subprocess.TimeoutExpired:
            raise FarmError(f"tessera {args[0]} took longer than {seconds} s: is the coordinator at {self.coordinator} answering?")
        except OSError as e:
            raise FarmError(f"could not run {self.binary}: {e}")
        if done.returncode != 0:
            raise FarmError(explain(done.stderr) or f"tessera {args[0]} failed (exit status {done.returncode})")
        return done.stdout

    def submit(self, scene, flags):
        """Submits `scene` with `flags`, detached; the render's id (`sN` for a sequence)."""
        out = self._run(["submit", scene, "--detach"] + list(flags), SUBMIT_SECONDS)
        lines = [l for l in out.split() if l.strip()]
        if not lines:
            raise FarmError("tessera submit printed no render id")
        return lines[-1]

    def status(self, render):
        """The render's status as `tessera status --json` gives it (a dict)."""
        rows = json.loads(self._run(["status", render, "--json"]))
        if not rows:
            raise FarmError(f"the coordinator does not list render {render}")
        return rows[0]

    def fetch(self, render, out, frames=None):
        """Downloads the render to `out` (a sequence's finished frames, of `frames` if given,
        to `out` with #s)."""
        extra = ["--frames", ",".join(str(f) for f in frames)] if frames else []
        self._run(["fetch", render, "--out", out] + extra, SUBMIT_SECONDS)

    def cancel(self, render):
        self._run(["cancel", render])


def explain(stderr):
    """The line of `stderr` that says what went wrong: the last `error:` line, without its
    prefix, else the last line."""
    lines = [l.strip() for l in stderr.splitlines() if l.strip()]
    errors = [l for l in lines if l.startswith("error:")]
    if errors:
        return errors[-1][len("error:"):].strip()
    return lines[-1] if lines else ""


def progress(status):
    """(fraction done, a short line for the panel) of a status dict."""
    total = status.get("passes_total") or 0
    fraction = (status.get("passes_done", 0) / total) if total else 0.0
    state = status.get("state", "?")
    frames = status.get("frames")
    if frames:
        line = f"{state}: {frames.get('done', 0)} of {frames.get('total', 0)} frames"
    else:
        line = f"{state}: {100 * fraction:.0f} %"
    if status.get("no_workers") and state == "running":
        line += " (no workers connected)"
    if status.get("message"):
        line += f" ({status['message']})"
    return fraction, line


def frame_pattern(path, frame=None):
    """The EXR path for Blender output `path` (absolute): its run of #s stands for the frame
    number (four are added when it has none, as Blender does); with `frame`, that frame's path."""
    head, tail = os.path.split(path)
    stem, ext = os.path.splitext(tail)
    # "shot.v2" has no image extension: all of it is the name.
    if ext.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr"):
        stem = tail
    if "#" not in stem:
        stem += "####"
    pattern = os.path.join(head, stem + ".exr")
    if frame is None:
        return pattern
    start = stem.index("#")
    width = len(stem[start:]) - len(stem[start:].lstrip("#"))
    named = stem[:start] + str(frame).zfill(width) + stem[start + width:]
    return os.path.join(head, named + ".exr")
