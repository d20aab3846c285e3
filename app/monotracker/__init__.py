"""MonoTracker: monocular, fully automatic CT-to-camera registration and real-time
APFF admittance tracking for a UR10 neurosurgical robot.

Layout and conventions: see ``ARCHITECTURE.md`` in the repository (one-way data flow
ct -> plan -> vision -> registration -> robot, engine owns state and threads, ui renders).
Transforms are 4x4 arrays named ``T_to_from`` (``T_cam_ct @ p_ct = p_cam``); CT, camera and
plan work in millimetres (LPS for CT), images in pixels, the robot side in metres and radians.
"""

__version__ = "0.1.0"
