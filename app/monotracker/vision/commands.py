"""``monotracker`` sub-commands of the vision area.

* ``calibrate-camera IMAGES... --chessboard 9x6 --square-mm 25 [--out camera.yml]`` (or
  ``--charuco 7x5 --square-mm 30 --marker-mm 22 [--dictionary DICT_5X5_100]``) ``[--ball-radius
  4]``: prints the RMS reprojection error, a note where the lens is short for the balls
  (:mod:`.lens_range`), and writes OpenCV YAML or JSON intrinsics.
* ``check-camera IMAGES... --camera camera.yml --chessboard 9x6 --square-mm 25``: checks a
  calibration against views of a known board taken now (focal length and principal point with
  their uncertainty; :func:`.calibration_check.check_with_board`); exit 0 when it agrees.
* ``detect-image IMAGE [--detector classical|learned] [--radius-mm 4] [--focal-px F | --camera FILE
  [--adapt bin:N|crop:X,Y,W,H]] [--annotate out.png] [--json]``: detects the fiducial balls in one
  image; with ``--camera`` an image whose size differs from the calibration is refused (one line)
  unless ``--adapt`` says the sensor was binned or cropped.

``simulate-camera`` (simulated frames to try these on) is the digital twin's: ``sim/commands.py``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from monotracker.cli_args import finite_float
from monotracker.errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate-camera", help="camera intrinsics from chessboard/ChArUco images")
    p.add_argument("images", nargs="+", help="calibration images (png/jpg)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--chessboard", metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    g.add_argument("--charuco", metavar="COLSxROWS", help="squares of a ChArUco board, e.g. 7x5")
    p.add_argument("--square-mm", type=float, required=True, help="square side in mm")
    p.add_argument("--marker-mm", type=float, help="ChArUco marker side in mm")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (ChArUco only)")
    p.add_argument("--out", default="camera.yml", help="output .yml/.yaml/.xml (OpenCV) or .json")
    p.add_argument("--ball-radius", type=finite_float(0.5, 20.0), default=4.0, metavar="MM",
                   help="the fiducial balls' radius in mm, for the lens check (default 4, the kit's): a lens "
                        "that images them under 10 px from 400 mm is named")
    p.set_defaults(func=_calibrate)

    c = subparsers.add_parser("check-camera", help="check a camera calibration against images of a known board")
    c.add_argument("images", nargs="+", help="images of the board, taken now with the camera as it is set up")
    c.add_argument("--camera", required=True, help="the calibration file to check (.yml/.yaml/.xml/.json)")
    c.add_argument("--chessboard", metavar="COLSxROWS", required=True, help="inner corners, e.g. 9x6")
    c.add_argument("--square-mm", type=float, required=True, help="square side in mm")
    c.add_argument("--adapt", default="", metavar="bin:N|scale:F|crop:X,Y,W,H",
                   help="the images come from the calibrated sensor binned or cropped")
    c.set_defaults(func=_check_camera)

    d = subparsers.add_parser("detect-image", help="detect the fiducial balls in one image")
    d.add_argument("image")
    d.add_argument("--detector", choices=("classical", "refined", "learned"), default="classical",
                   help="classical (the default); refined: classical with the learned centre refiner (issue 28, "
                        "research only, NOT for clinical use: half the centre error on Mitsuba frames like its "
                        "training frames, 3-6x worse on other renders); "
                        "learned: NOT for clinical use (trained on a simple render only)")
    d.add_argument("--radius-mm", type=float, default=4.0, help="ball radius (mm)")
    d.add_argument("--focal-px", type=float, default=None, help="focal length (px) for the size check")
    d.add_argument("--camera", default=None, help="camera calibration file (gives the focal length); the image "
                   "must have the calibrated size")
    d.add_argument("--adapt", default="", metavar="bin:N|scale:F|crop:X,Y,W,H",
                   help="the image comes from the calibrated sensor binned or cropped: adapt the calibration")
    d.add_argument("--annotate", default=None, help="write an annotated copy of the image here")
    d.add_argument("--json", action="store_true", help="print JSON instead of a table")
    d.set_defaults(func=_detect)


def _calibrate(args) -> int:
    from .calibration import calibrate_charuco, calibrate_chessboard, parse_pattern
    from .lens_range import short_lens_message

    if args.chessboard:
        res = calibrate_chessboard(args.images, parse_pattern(args.chessboard), args.square_mm)
    else:
        if args.marker_mm is None:
            raise InputError("--charuco needs --marker-mm")
        res = calibrate_charuco(args.images, parse_pattern(args.charuco), args.square_mm, args.marker_mm,
                                args.dictionary)
    for name, why in res.skipped.items():
        print(f"skipped {name}: {why}")
    print(res.summary())
    print(f"RMS reprojection error: {res.rms_px:.3f} px")
    lens = short_lens_message(res.camera, args.ball_radius)
    if lens:
        print(f"note: {lens}")
    out = res.camera.save(args.out)
    print(f"wrote {out}")
    return 0


def _check_camera(args) -> int:
    """Exit 0 when the calibration agrees with the board, 1 when it does not or the views cannot
    tell (the line says which and what to do), 2 for bad input."""
    from .calibration import chessboard_views, parse_pattern
    from .calibration_check import check_with_board
    from .camera_model import CameraModel

    model = CameraModel.load(args.camera).adapted(args.adapt)
    obj, img, names, skipped, size = chessboard_views(args.images, parse_pattern(args.chessboard), args.square_mm)
    if tuple(size) != tuple(model.image_size):
        raise InputError(f"the images are {size[0]}x{size[1]} px but the calibration is for "
                         f"{model.width}x{model.height}: take them with the camera as it is set up, or use --adapt")
    for name, why in skipped.items():
        print(f"skipped {name}: {why}")
    if not obj:
        raise InputError("the board was found in none of the images")
    res = check_with_board(model, obj, img)
    print(res.message)
    return 0 if res.ok else 1


def _detect(args) -> int:
    import cv2

    from .detection import BlobRules

    path = Path(args.image)
    if not path.is_file():
        raise InputError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"cannot read image {path.name} (corrupt or not an image)")
    from .frames import grayscale_problem

    grey = grayscale_problem(img)
    if grey:
        raise InputError(f"{path.name}: {grey}")
    focal, model = args.focal_px, None
    if args.camera:
        from .camera_model import CameraModel

        model = CameraModel.load(args.camera).adapted(args.adapt)
        problem = model.frame_size_problem(img.shape)
        if problem:
            raise InputError(f"{path.name}: {problem}")
        focal = float(model.K[0, 0])
    elif args.adapt:
        raise InputError("--adapt needs --camera (the calibration to adapt)")
    if focal is None:
        focal = 1100.0 * img.shape[1] / 1280.0
    # with a calibration, each ball's outline is a whole sphere's at its place (sphere_outline)
    rules = BlobRules(radius_mm=args.radius_mm, focal_px=focal, camera=model)
    if args.detector == "learned":
        from .detect_learned import NOT_FOR_CLINICAL_USE, LearnedDetector

        print(NOT_FOR_CLINICAL_USE, file=sys.stderr)
        det = LearnedDetector(rules=rules)
    else:
        from .detect_classical import ClassicalDetector

        refiner = None
        if args.detector == "refined":
            from .centre_refiner import NOT_FOR_CLINICAL_USE as REFINER_WARNING
            from .centre_refiner import CentreRefiner

            print(REFINER_WARNING, file=sys.stderr)
            refiner = CentreRefiner()
        det = ClassicalDetector(rules, refiner=refiner)
    res = det.detect(img)
    if args.json:
        print(json.dumps({"detector": res.detector, "time_ms": 1000 * res.time_s, "fiducials": [
            {"centre_px": f.centre_px.round(3).tolist(), "axes_px": [round(a, 3) for a in f.axes_px],
             "angle_deg": round(f.angle_deg, 2), "score": round(f.score, 3)} for f in res.fiducials],
            "rejected": [{"centre_px": f.centre_px.round(1).tolist(), "reason": f.reason} for f in res.rejected]},
            indent=1))
    else:
        print(f"{len(res.fiducials)} fiducials ({res.detector}, {1000 * res.time_s:.1f} ms)")
        print(f"{'#':>3} {'u px':>9} {'v px':>9} {'a px':>6} {'b px':>6} {'angle':>6} {'score':>5}")
        for i, f in enumerate(res.fiducials):
            print(f"{i:>3} {f.centre_px[0]:9.2f} {f.centre_px[1]:9.2f} {f.axes_px[0]:6.2f} {f.axes_px[1]:6.2f} "
                  f"{f.angle_deg:6.1f} {f.score:5.2f}")
        for f in res.rejected:
            print(f"rejected at ({f.centre_px[0]:.0f}, {f.centre_px[1]:.0f}): {f.reason}")
    if args.annotate:
        out = img.copy()
        for f in res.fiducials:
            c = tuple(int(round(x)) for x in f.centre_px)
            cv2.ellipse(out, (c, (2 * f.axes_px[0], 2 * f.axes_px[1]), f.angle_deg), (0, 0, 255), 1, cv2.LINE_AA)
            cv2.drawMarker(out, c, (0, 0, 255), cv2.MARKER_CROSS, 6)
        for f in res.rejected:
            c = tuple(int(round(x)) for x in f.centre_px)
            cv2.drawMarker(out, c, (0, 200, 255), cv2.MARKER_TILTED_CROSS, 10)
        if not cv2.imwrite(args.annotate, out):
            raise InputError(f"cannot write {args.annotate}")
    return 0
