"""Receive MonoTracker's OpenIGTLink stream as 3D Slicer would (pose, needle, fiducials, status).

What it shows: ``monotracker.interop.igtl`` streaming from a running session to an OpenIGTLink
client (``pyigtl``, the protocol's Python implementation from the Slicer team) on 127.0.0.1:
TRANSFORM ``CTToCamera`` (CT to camera, mm), TRANSFORM ``NeedleTipToCT`` (the needle tip in the
CT), POINT ``Fiducials`` and ``Path`` (entry, target) and STRING ``Status``. The CT side is in
Slicer's RAS (so a CT loaded in Slicer lines up); multiply by diag(-1, -1, 1, 1) to get
MonoTracker's LPS. A pose is only sent while the engine trusts it; ``Status`` says
``pose=VALID`` or why not. Here the session is the headless demo on a simulated clock; with the
web app, ``monotracker serve --igtl-port 18944`` streams the same, and Slicer's OpenIGTLinkIF
module connects to it. Exits non-zero if no rigid ``CTToCamera`` arrives.

Run: ``python examples/08_openigtlink_client.py [--port 18944]``
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
from pathlib import Path

import numpy as np
import pyigtl

from monotracker.demo.run import DemoOptions, run_demo


class _EveryMessage(dict):
    """pyigtl keeps each device's newest message; keep every one, in arrival order."""

    def __init__(self):
        super().__init__()
        self.all = []

    def __setitem__(self, key, msg):
        self.all.append(msg)
        super().__setitem__(key, msg)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=int, default=0, help="OpenIGTLink port (default: a free one)")
    args = ap.parse_args(argv)
    port = args.port or free_port()

    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port, start_now=False)
    client.incoming_messages = _EveryMessage()
    client.start()
    try:
        with tempfile.TemporaryDirectory(prefix="monotracker-example-") as home:     # removed at the end
            run_demo(DemoOptions(seconds=2.0, home=Path(home), igtl_port=port))
    finally:
        client.stop()
    by_device = {}
    for m in client.incoming_messages.all:
        by_device.setdefault(m.device_name, []).append(m)
    for name, msgs in sorted(by_device.items()):
        print(f"{name}: {len(msgs)} messages ({msgs[-1].message_type})")
    poses = by_device.get("CTToCamera", [])
    if not poses:
        print("no CTToCamera message arrived")
        return 1
    T = np.asarray(poses[-1].matrix, float)
    R = T[:3, :3]
    rigid = np.abs(R.T @ R - np.eye(3)).max() < 1e-5 and abs(np.linalg.det(R) - 1) < 1e-5
    print("last CTToCamera (RAS CT -> camera, mm):")
    print(np.array2string(T, precision=3, suppress_small=True))
    print("last Status:", by_device["Status"][-1].string if "Status" in by_device else "-")
    return 0 if rigid else 1


if __name__ == "__main__":
    sys.exit(main())
