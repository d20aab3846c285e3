"""CameraRig on the vision and registration packages (filled in when they land)."""

from monotracker.errors import MonoTrackerError


def make_vision_rig(source, calibration_path, plan, cfg, session):
    raise MonoTrackerError("the camera pipeline (vision + registration) is not available in this build yet")
