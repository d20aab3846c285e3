"""The camera source kinds, in one table: how a source is written, checked and turned into a rig.

A camera source is ``KIND`` or ``KIND:ARG``. :data:`SOURCES` has one row per kind; every way a
source enters uses it: ``SessionConfig.validate`` and ``Session.set_camera`` check a spec with
:func:`source_problem`, the rig factory (``rigs/factory.py``) builds the rig with the row's
``build``, the web app lists the rows' ``example`` and the ``serve --camera`` help shows
:data:`GRAMMAR`. Adding a camera source is adding a row (and, for a new kind of frame source, its
class in ``vision/frames.py``).

Each ``build(arg, calibration_path, plan, cfg, session, rules)`` returns a
:class:`~monotracker.engine.rigs.base.CameraRig`; ``arg`` is the part after the colon, already
checked; ``rules`` are the session's per-frame trust rules (``SessionConfig.frame_rules``), which the
rig's pose tracker applies to every estimate.

The kinds: ``"sim"`` the rendered digital-twin camera (vision's
SimulatedCamera + classical detector + PoseTracker), ``"sim-points"`` the twin at the level of
detected points (no rendering), ``"device:N" | "file:PATH" | "folder:PATH"`` real sources through
vision's PoseStream (clock="real"; pass the calibration file to ``set_camera``). Per-fiducial
statuses in ``snap.pose.fiducial_status`` use vision's words: ``"seen" | "newly_lost" |
"occluded" | "unknown"``, keyed by fiducial id.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from monotracker.errors import InputError


def _sim_image(arg, calibration_path, plan, cfg, session, rules):
    from monotracker.engine.rigs.sim import SimImageRig

    return SimImageRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps,
                       optics=getattr(cfg, "camera_optics", None), rules=rules)


def _sim_points(arg, calibration_path, plan, cfg, session, rules):
    from monotracker.engine.rigs.sim import ProjectedFiducialRig

    return ProjectedFiducialRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps, rules=rules)


def _stream(kind: str):
    def build(arg, calibration_path, plan, cfg, session, rules):
        from monotracker.engine.rigs.stream import StreamRig

        return StreamRig(kind, arg, calibration_path, plan, session, camera_adapt=cfg.camera_adapt, rules=rules)
    return build


def _device_number(arg: str) -> str | None:
    return None if arg.isdigit() else "camera device must be a number, as in device:0"


def _path(what: str):
    def check(arg: str) -> str | None:
        return None if arg.strip() else f"give the {what} after the colon"
    return check


@dataclass(frozen=True)
class SourceKind:
    """One kind of camera source. ``kind`` as written before the colon; ``example`` as offered to
    the operator (``PATH``, ``DIR``, ``N`` to be filled in); ``simulated``: the digital twin (any clock;
    faults can be injected); ``real_clock``: needs a real-clock session (its own thread);
    ``check_arg(arg)``: None or why the argument is wrong (None: the kind takes no argument);
    ``build``: see the module docstring; ``describe``: one line for help texts."""

    kind: str
    example: str
    simulated: bool
    real_clock: bool
    check_arg: Callable[[str], str | None] | None
    build: Callable
    describe: str


SOURCES: dict[str, SourceKind] = {
    "sim": SourceKind("sim", "sim", True, False, None, _sim_image,
                      "the rendered digital-twin camera (vision's detector and registration)"),
    "sim-points": SourceKind("sim-points", "sim-points", True, False, None, _sim_points,
                             "the twin at the level of detected points (no rendering)"),
    "device": SourceKind("device", "device:0", False, True, _device_number, _stream("device"),
                         "a camera device by number"),
    "file": SourceKind("file", "file:PATH", False, True, _path("video file"), _stream("file"), "a video file"),
    "folder": SourceKind("folder", "folder:PATH", False, True, _path("image folder"), _stream("folder"),
                         "a folder of images"),
    "replay": SourceKind("replay", "replay:DIR", False, True, _path("recording folder"), _stream("replay"),
                         "a session recording (monotracker.engine.recording), paced at its frame times"),
}
#: how a source is written, for messages and help texts
GRAMMAR = ", ".join(f"'{k.example.replace(':0', ':N')}'" for k in SOURCES.values())


def parse_source(spec) -> tuple[SourceKind, str]:
    """``(kind, argument)`` of a camera source; :class:`InputError` with one line when it is wrong."""
    spec = str(spec)
    name, sep, arg = spec.partition(":")
    kind = SOURCES.get(name)
    if kind is None or bool(sep) != (kind.check_arg is not None):
        raise InputError(f"camera must be one of {GRAMMAR}, not {spec!r}")
    why = kind.check_arg(arg) if kind.check_arg is not None else None
    if why:
        raise InputError(f"{why} (got {spec!r})")
    return kind, arg


def source_problem(spec) -> str | None:
    """None for a valid camera source, else one line saying what is wrong."""
    try:
        parse_source(spec)
    except InputError as exc:
        return str(exc)
    return None
