"""`stereoseed calibrate` and `stereoseed target`: the pair's calibration and the printable target."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError

def _cmd_calibrate(args: argparse.Namespace) -> int:
    from stereoseed.io.files import write_json

    if Path(args.output).is_dir():
        raise StereoseedError(f"{args.output}: is a folder; give the calibration file to write, e.g. calib.json")
    cameras = _calibrate_from_target(args) if args.target else _calibrate_from_points(args)
    write_json(args.output, {"cameras": cameras})
    print(f"wrote {args.output}")
    return 0

def _calibrate_from_points(args: argparse.Namespace) -> list[dict]:
    """The paper's form: a pattern file and the pixels of its points in each pair image."""
    from stereoseed.estimators.calibration import calibrate_camera
    from stereoseed.io.files import read_points_file
    from stereoseed.calibration.lens_calibration import calibrate_lens

    if len(args.inputs) != 3 or args.lens_images1 or args.lens_images2:
        raise StereoseedError("calibrate: give PATTERN POINTS1 POINTS2 (typed points), or --target target.json "
                              "IMAGE1 IMAGE2 (photos of the printed target, with --lens-images1/2)")
    pattern_path, *point_paths = args.inputs
    pattern = read_points_file(pattern_path, 3)
    cameras = []
    for i, path in enumerate(point_paths, 1):
        pixels = read_points_file(path, 2)
        if len(pixels) != len(pattern):
            raise StereoseedError(f"{path}: {len(pixels)} image points but {len(pattern)} pattern points "
                                  f"in {pattern_path}; give one pixel per pattern point, same order")
        if args.lens:
            cal = calibrate_lens([(pattern, pixels)], k3=args.k3, what=[str(path)])
            entry, rms, K = cal.to_dict(), cal.rms_px[0], cal.K
            centre = -cal.R[0].T @ cal.t[0]
        else:
            single = calibrate_camera(pattern, pixels, what=str(path))
            entry, rms, K, centre = single.to_dict(), single.rms_px, single.K, -single.R.T @ single.t
        cameras.append(entry)
        print(f"camera {i}: {len(pattern)} points, reprojection RMS {rms:.3f} px, "
              f"f = ({K[0, 0]:.1f}, {K[1, 1]:.1f}) px, centre = {np.round(centre, 4).tolist()}"
              + (f", distortion {np.round(entry['distortion'], 4).tolist()}" if args.lens else ""))
    return cameras

def _calibrate_from_target(args: argparse.Namespace) -> list[dict]:
    """Photos of the printed target: corners found, the camera and its lens estimated per
    physical camera from the pair image and its --lens-images; a check PNG per image."""
    from stereoseed.io.files import read_image
    from stereoseed.calibration.lens_calibration import calibrate_from_target, read_opencv_intrinsics
    from stereoseed.calibration.target import load_target
    from stereoseed.output.visualize import draw_calibration_check

    if len(args.inputs) != 2:
        raise StereoseedError("calibrate --target target.json: give the two images of the calibrated pair")
    target = load_target(args.target)
    cameras = []
    out = Path(args.output)
    for i, (image, more, intrinsics) in enumerate(((args.inputs[0], args.lens_images1, args.intrinsics1),
                                                   (args.inputs[1], args.lens_images2, args.intrinsics2)), 1):
        paths = [image] + list(more or [])
        images = [(str(p), read_image(p)) for p in paths]
        known = read_opencv_intrinsics(intrinsics) if intrinsics else None
        cal, checks = calibrate_from_target(target, images, k3=args.k3, intrinsics=known)
        cameras.append(cal.to_dict())
        for check, (path, img) in zip(checks, images):
            png = out.with_name(f"{out.stem}_{Path(path).stem}.png")
            draw_calibration_check(img, check.detected, check.reprojected, png)
            faces = ", ".join(f"face {f}: {n}" for f, n in sorted(check.per_face.items()))
            print(f"camera {i}, {path}: {faces} corners, RMS {check.rms_px:.3f} px, {100 * check.coverage:.0f} % of "
                  f"the frame; check {png}")
            for w in check.warnings:
                print(f"stereoseed: warning: {path}: {w}", file=sys.stderr)
        print(f"camera {i}: f = ({cal.K[0, 0]:.1f}, {cal.K[1, 1]:.1f}) px, distortion "
              f"{np.round(cal.distortion, 4).tolist()}, centre {np.round(-cal.R[0].T @ cal.t[0], 1).tolist()}")
    return cameras

def _cmd_target(args: argparse.Namespace) -> int:
    from stereoseed.calibration.target import make_target

    path = make_target(Path(args.out), size=args.size, faces=args.faces)
    names = ", ".join(f"face_{k}.png" for k in range(args.faces))
    print(f"wrote {names} (print at 100 %), assembly.png and {path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the calibrate, target subcommands."""
    p = sub.add_parser("calibrate", help="calibrate the stereo pair: from photos of the printed target (--target), "
                                         "or from a 3D pattern's typed points (DLT + LM)")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="IMAGE1 IMAGE2 with --target; else PATTERN POINTS1 POINTS2 (text files: 'X Y Z' per known "
                        "3D point, and the pixel 'u v' of each in image 1 and 2, same order)")
    p.add_argument("--target", help="target.json of the printed target (stereoseed target)")
    p.add_argument("--lens-images1", nargs="+", help="more photos of the target by camera 1 (the lens over the frame)")
    p.add_argument("--lens-images2", nargs="+", help="more photos of the target by camera 2")
    p.add_argument("--intrinsics1", help="camera 1's known intrinsics and lens (OpenCV FileStorage YAML/JSON)")
    p.add_argument("--intrinsics2", help="camera 2's known intrinsics and lens (OpenCV FileStorage YAML/JSON)")
    p.add_argument("--lens", action="store_true", help="typed points: also estimate the lens distortion")
    p.add_argument("--k3", action="store_true", help="also estimate the third radial term (wide-angle lenses)")
    p.add_argument("-o", "--output", default="calib.json", help="calib.json to write (default: %(default)s)")
    p.set_defaults(func=_cmd_calibrate)


    p = sub.add_parser("target", help="write a printable 3D calibration target (ChArUco boards for 2 or 3 faces of a box)")
    p.add_argument("--out", required=True, help="folder for face_<k>.png, assembly.png and target.json")
    p.add_argument("--size", choices=["A4", "A3", "letter"], default="A4", help="paper size (default: %(default)s)")
    p.add_argument("--faces", type=int, choices=[2, 3], default=3, help="faces of the box to cover (default: 3)")
    p.set_defaults(func=_cmd_target)

