"""`stereoseed calibrate`, `stereoseed intrinsics` and `stereoseed target`: the pair's calibration,
one camera's intrinsics from a (flat or 3D) target, and the printable target."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stereoseed.cli._terminal import say, warn
from stereoseed.errors import StereoseedError
from stereoseed.io.outputs import record_written_file, refuse_foreign_file, refuse_input_as_output, same_file


def _config(args: argparse.Namespace):
    from stereoseed.calibration.config import CalibrationConfig

    if args.max_rms is not None and not args.max_rms > 0:
        raise StereoseedError(f"--max-rms {args.max_rms:g}: give a limit in pixels above 0")
    return CalibrationConfig(max_rms_px=args.max_rms, strict=args.strict)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from stereoseed.api import calibrate

    if Path(args.output).is_dir():
        raise StereoseedError(f"{args.output}: is a folder; give the calibration file to write, e.g. calib.json")
    inputs = _calibrate_inputs(args)
    refuse_input_as_output(args.output, inputs, "give another -o")
    refuse_foreign_file(args.output, "give another -o")
    if args.target:
        refined = _refined_target_path(Path(args.output))
        refuse_input_as_output(refined, inputs, "give another -o (the target as found goes to <stem of -o>_target.json)")
        refuse_foreign_file(refined, "give another -o (the target as found goes to <stem of -o>_target.json)")
        for png in _check_images(Path(args.output), _photos(args), inputs).values():
            refuse_foreign_file(png, "give another -o (the check images are <stem of -o>_cam<N>_<photo>.png)")
    if not args.target:
        pair = calibrate(args.inputs, lens_images=(args.lens_images1 or [], args.lens_images2 or []), rig=args.rig,
                         lens=args.lens, k3=args.k3, cfg=_config(args))
        for i, cam in enumerate(pair.cameras, 1):
            say(f"camera {i}: {cam.n_points} points, reprojection RMS {cam.rms_px:.3f} px, "
                f"f = ({cam.K[0, 0]:.1f}, {cam.K[1, 1]:.1f}) px, centre = {np.round(cam.centre, 4).tolist()}"
                + (f", distortion {np.round(cam.distortion, 4).tolist()}" if cam.distortion is not None else ""))
        for w in pair.warnings:
            warn(w)
    else:
        pair = _calibrate_from_target(args)
    record_written_file(pair.write(args.output))
    say(f"wrote {args.output}")
    return 0


def _calibrate_inputs(args: argparse.Namespace) -> list:
    """Every file `calibrate` reads (None: an option not given)."""
    return [*args.inputs, args.target, *(args.lens_images1 or []), *(args.lens_images2 or []), args.intrinsics1,
            args.intrinsics2]


def _photos(args: argparse.Namespace) -> list[list[str]]:
    """`calibrate --target`'s photos per camera, as its views are named: the pair's photo first,
    then the lens photos (some of which the calibration may drop or skip)."""
    return [[str(args.inputs[c]), *map(str, lens or [])] for c, lens in
            enumerate((args.lens_images1, args.lens_images2)) if c < len(args.inputs)]


def _refined_target_path(out: Path) -> Path:
    """Where `calibrate --target` writes the target as found: beside calib.json."""
    return out.with_name(f"{out.stem}_target.json")


def _detect_all(target, paths: list[str]) -> list:
    """Each image read and its target corners found; a view that cannot be read is the user's
    error (one line), a view without the target is judged later (skipped with its reason)."""
    from stereoseed.calibration.detection import detect_target

    return [detect_target(p, target, what=str(p)) for p in paths]


def _unique_png(out: Path, camera: int, image: str, taken: set[str], inputs: list) -> Path:
    """calib_cam1_7.png: the check image of camera 1's photo 7.jpg, unique within the run and
    never one of the run's inputs (a photo named so gets calib_cam1_7_2.png)."""
    base = f"{out.stem}_cam{camera}_{Path(image).stem}"
    name, n = base, 1
    while name in taken or any(i is not None and same_file(out.with_name(name + ".png"), i) for i in inputs):
        n += 1
        name = f"{base}_{n}"
    taken.add(name)
    return out.with_name(name + ".png")


def _check_images(out: Path, photos: list[list[str]], inputs: list) -> dict[tuple[int, str], Path]:
    """{(camera index, photo): its check image} for every photo of the run, named before the work
    (so that the writers' rule is applied to all of them before it) and the same whichever views
    the calibration then skips."""
    taken: set[str] = set()
    planned: dict[tuple[int, str], Path] = {}
    for c, names in enumerate(photos):
        for name in names:
            if (c, name) not in planned:
                planned[c, name] = _unique_png(out, c + 1, name, taken, [*inputs, out])
    return planned


def _report_views(cal, labels: list[str], checks: dict[tuple[int, str], Path] | None = None) -> None:
    """A line per photo (corners per face, RMS, its check image of ``checks``, where given), a
    warning per skipped one."""
    from stereoseed.io.files import read_image
    from stereoseed.output.visualize import draw_calibration_check

    for c, cam in enumerate(cal.cameras):
        for v in cam.views:
            if not v.used:
                warn(f"{labels[c]}, {v.name}: skipped: {v.reason}")
                continue
            line = f"{labels[c]}, {v.name}: {v.detection.summary()}, RMS {v.rms_px:.3f} px"
            if checks is not None:
                png = checks[c, v.name]
                draw_calibration_check(read_image(v.name), v.detection.pixels, v.reprojected, png)
                record_written_file(png)
                line += f"; check {png}"
            say(line)


def _report_cameras(cal, labels: list[str]) -> None:
    min_coverage = 1 / 3  # below this share of the frame the lens is extrapolated where no corner was
    for c, cam in enumerate(cal.cameras):
        used = sum(v.used for v in cam.views)
        say(f"{labels[c]}: {used} view(s), {cam.n_points} corners, RMS {cam.rms_px:.3f} px, f = ({cam.K[0, 0]:.1f}, "
              f"{cam.K[1, 1]:.1f}) px, principal point ({cam.K[0, 2]:.1f}, {cam.K[1, 2]:.1f}), distortion "
              f"{np.round(cam.lens, 4).tolist()}" + (" (given)" if cam.known else ""))
        if not cam.known and cam.coverage < min_coverage:
            warn(f"{labels[c]}: the corners of its views cover {100 * cam.coverage:.0f} % of the frame: the lens is "
                  "poorly determined outside them (add views with the target elsewhere in the frame)")
    moved = [(f, m) for f, m in enumerate(cal.face_moves) if m is not None]
    if moved:
        say("target: faces found " + ", ".join(f"face {f} {mm:.2f} mm / {deg:.2f} deg" for f, (mm, deg) in moved)
              + " from where target.json puts them")
    if cal.rig is not None:
        spread = ("" if cal.rig.spread_mm is None else
                  f"; uncertainty +-{cal.rig.uncertainty_mm:.2f} mm, +-{cal.rig.uncertainty_deg:.2f} deg (leaving "
                  f"out one shot, the intrinsics re-estimated too, moves it by up to {cal.rig.spread_mm:.2f} mm, "
                  f"{cal.rig.spread_deg:.3f} deg)")
        say(f"rig: camera 2 from camera 1: baseline {cal.rig.baseline_mm:.2f} mm, rotation {cal.rig.angle_deg:.2f} deg, "
              f"from {cal.rig.shots} shots{spread}")
    for note in cal.notes:
        say(f"note: {note}")
    for w in cal.warnings:
        warn(w)


def _calibrate_from_target(args: argparse.Namespace):
    """Photos of the target (:func:`stereoseed.api.calibrate`): a line per photo and camera, a
    check PNG per photo and the refined target beside calib.json."""
    from stereoseed.api import calibrate

    out = Path(args.output)
    labels = ["camera 1", "camera 2"]
    if (not args.rig and args.lens_images1 and args.lens_images2
            and len(args.lens_images1) == len(args.lens_images2)):
        say("note: as many lens photos for both cameras; if each pair was taken together by the fixed pair, --rig "
            "estimates one relative pose from all of them")
    pair = calibrate(args.inputs, target=args.target, lens_images=(args.lens_images1 or [], args.lens_images2 or []),
                     intrinsics=(args.intrinsics1, args.intrinsics2), rig=args.rig, rigid_target=args.rigid_target,
                     k3=args.k3, cfg=_config(args))
    _report_views(pair.calibration, labels, _check_images(out, _photos(args), _calibrate_inputs(args)))
    _report_cameras(pair.calibration, labels)
    refined = pair.write_target(_refined_target_path(out))
    record_written_file(refined)
    say(f"wrote {refined} (the target as found: give it with --rigid-target to keep it)")
    return pair


def _image_list(items: list[str]) -> list[Path]:
    from stereoseed.io.files import list_images

    paths: list[Path] = []
    for item in items:
        paths += list_images(item) if Path(item).is_dir() else [Path(item)]
    return paths


def _cmd_intrinsics(args: argparse.Namespace) -> int:
    """One camera from its photos of a target (a flat board or a 3D one): Zhang's closed form,
    then every view and the lens refined; an OpenCV calibration file out."""
    from stereoseed.calibration.lens_calibration import write_opencv_camera
    from stereoseed.calibration.rig import calibrate_cameras
    from stereoseed.calibration.target import load_target

    out = Path(args.output)
    if out.suffix.lower() not in (".yaml", ".yml", ".xml", ".json"):
        raise StereoseedError(f"{out}: give a .yaml, .yml, .xml or .json file to write the camera into")
    cfg = _config(args)
    paths = _image_list(args.images)
    refuse_input_as_output(out, [args.target, *paths], "give another -o")
    refuse_foreign_file(out, "give another -o")
    # a check image per photo, <stem of -o>_cam1_<photo>.png, as calibrate writes them
    checks = _check_images(out, [[str(p) for p in paths]], [args.target, *paths])
    for png in checks.values():
        refuse_foreign_file(png, "give another -o (the check images are <stem of -o>_cam1_<photo>.png)")
    target = load_target(args.target)
    detections = _detect_all(target, [str(p) for p in paths])
    cal = calibrate_cameras(target, [detections], rigid_target=args.rigid_target, k3=args.k3, cfg=cfg, pair=False,
                            labels=["camera"])
    _report_views(cal, ["camera"], checks)
    _report_cameras(cal, ["camera"])
    cam = cal.cameras[0]
    write_opencv_camera(out, cam.K, cam.lens, cam.image_size, cam.rms_px,
                        [(v.name, v.rms_px) for v in cam.views if v.used])
    record_written_file(out)
    say(f"wrote {out} (give it to calibrate with --intrinsics1 or --intrinsics2)")
    return 0


def _cmd_target(args: argparse.Namespace) -> int:
    from stereoseed.calibration.printing import box_size_mm, make_target

    path = make_target(Path(args.out), size=args.size, faces=args.faces, force=args.force)
    names = ", ".join(f"face_{k}.png/.pdf" for k in range(args.faces))
    x, y, z = box_size_mm(args.size, args.faces)
    say(f"wrote {names} (print the PDFs at 100 %, or the PNGs at 300 dpi), assembly.png and {path}")
    say(f"glue them on a box of at least {x:.0f} x {y:.0f} x {z:.0f} mm (x, y, z) as assembly.png shows")
    return 0


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    """The options of a camera fit, shared by calibrate and intrinsics."""
    p.add_argument("--k3", action="store_true", help="also estimate the third radial term (wide-angle lenses)")
    p.add_argument("--rigid-target", action="store_true",
                   help="keep the target's faces where target.json puts them (default: estimate where they are)")
    p.add_argument("--max-rms", type=float, metavar="PX",
                   help="refuse a camera whose corners reproject worse than this RMS (default: only a warning)")
    p.add_argument("--strict", action="store_true",
                   help="refuse a calibration whose own checks disagree (a rig weakly determined or off its shots' "
                        "evidence) instead of writing it with a warning")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the calibrate, intrinsics and target subcommands."""
    p = sub.add_parser("calibrate", help="calibrate the stereo pair: from photos of a target (--target), "
                                         "or from a 3D pattern's typed points (DLT + LM)")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="IMAGE1 IMAGE2 with --target; else PATTERN POINTS1 POINTS2 (text files: 'X Y Z' per known "
                        "3D point, and the pixel 'u v' of each in image 1 and 2, same order)")
    p.add_argument("--target", help="target.json of the target (stereoseed target, or examples/)")
    p.add_argument("--lens-images1", nargs="+", help="more photos of the target by camera 1 (the lens over the frame)")
    p.add_argument("--lens-images2", nargs="+", help="more photos of the target by camera 2")
    p.add_argument("--rig", action="store_true",
                   help="the pair is fixed and took each lens photo together (--lens-images1/2 as many, in the same "
                        "order): one relative pose from every shot, its leave-one-out spread reported")
    p.add_argument("--intrinsics1", help="camera 1's known intrinsics and lens (OpenCV FileStorage YAML/XML/JSON)")
    p.add_argument("--intrinsics2", help="camera 2's known intrinsics and lens (OpenCV FileStorage YAML/XML/JSON)")
    p.add_argument("--lens", action="store_true", help="typed points: also estimate the lens distortion")
    _add_fit_options(p)
    p.add_argument("-o", "--output", default="calib.json", help="calib.json to write (default: %(default)s)")
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("intrinsics", help="one camera's intrinsics and lens from its photos of a target (a flat board "
                                          "or a 3D one), written as an OpenCV calibration file")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="photos of the target by one camera (or folders of them)")
    p.add_argument("--target", required=True, help="target.json of the target")
    _add_fit_options(p)
    p.add_argument("-o", "--output", default="camera.yaml", help="the file to write (default: %(default)s)")
    p.set_defaults(func=_cmd_intrinsics)

    p = sub.add_parser("target", help="write a printable 3D calibration target (ChArUco boards for 2 or 3 faces of a box)")
    p.add_argument("--out", required=True, help="folder for face_<k>.png/.pdf, assembly.png and target.json")
    p.add_argument("--size", choices=["A4", "A3", "letter"], default="A4", help="paper size (default: %(default)s)")
    p.add_argument("--faces", type=int, choices=[2, 3], default=3, help="faces of the box to cover (default: 3)")
    p.add_argument("--force", action="store_true", help="write into a folder that holds other files too")
    p.set_defaults(func=_cmd_target)
