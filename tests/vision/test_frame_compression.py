"""Frame sources say when their frames come through a lossy coding (``FrameSource.compression``):
checked on files OpenCV itself wrote with a known codec."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from monotracker.vision.frames import ImageFolderSource, VideoFileSource, fourcc_name, lossy_coding


def _write_video(path, fourcc: str) -> bool:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (320, 240))
    if not w.isOpened():
        return False
    rng = np.random.default_rng(0)
    for _ in range(3):
        w.write(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    w.release()
    return path.is_file() and path.stat().st_size > 0


@pytest.mark.parametrize("fourcc, expect", [("MJPG", "MJPEG"), ("FFV1", ""), ("XVID", "video codec")])
def test_video_file_names_its_lossy_codec(tmp_path, fourcc, expect):
    path = tmp_path / f"v_{fourcc}.avi"
    if not _write_video(path, fourcc):
        pytest.skip(f"this OpenCV build cannot write {fourcc}")
    src = VideoFileSource(path)
    try:
        assert (src.compression.startswith(expect) if expect else src.compression == ""), src.compression
    finally:
        src.close()


def test_image_folder_with_jpeg_files_is_lossy(tmp_path):
    img = np.full((48, 64, 3), 120, np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    assert ImageFolderSource(tmp_path).compression == ""
    cv2.imwrite(str(tmp_path / "b.jpg"), img)
    assert ImageFolderSource(tmp_path).compression == "JPEG files"


def test_fourcc_decoding():
    code = float(cv2.VideoWriter_fourcc(*"MJPG"))
    assert fourcc_name(code) == "MJPG" and lossy_coding("MJPG") == "MJPEG"
    assert fourcc_name(0.0) == "" and lossy_coding("") == ""       # unknown: no claim
    assert fourcc_name(-1.0) == "" and fourcc_name(float("nan")) == ""   # a backend without it
    assert fourcc_name(float(0xFF_FF_FF_7F)) == ""                 # not ASCII
    assert lossy_coding("YUYV") == "" and lossy_coding("avc1") == "video codec 'avc1'"
    assert lossy_coding("mjpg") == "MJPEG"
    for raw in ("RGB3", "BA81", "NV21", "YU12", "Y10 ", "FFV1"):   # raw V4L2 / lossless: no claim
        assert lossy_coding(raw) == "", raw
