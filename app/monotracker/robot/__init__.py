"""Robot side: UR10 kinematics (pinocchio + POE), APFF admittance controller, safety layer,
arm backends (simulated, ur_rtde) and hand-eye calibration. Metres/radians inside; the public
tracker API takes millimetres (see ``units.py``)."""
