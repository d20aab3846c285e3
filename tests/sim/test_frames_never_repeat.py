"""A live sensor never repeats a frame bit for bit: the engine reads identical frames as a frozen
camera (issue 33). The rendered twin of a still head, with frames skipped as a busy machine skips
them, must not either."""

import zlib

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.trajectories import Still


def test_a_still_heads_frames_never_repeat_even_with_frames_skipped():
    cam = SimulatedCamera(trajectory=Still(), seed=0)
    digests = [zlib.crc32(cam.render(i / 30)[0].data) for i in range(24)]
    # any two frames (a busy machine hands the engine every 2nd or 3rd one): never the same
    # (the bank of 6 noise images alone repeated every 2nd frame one time in five)
    assert len(set(digests)) == len(digests)
