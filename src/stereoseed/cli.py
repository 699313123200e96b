"""Command-line interface: each subcommand is a few lines over the Python API.

Errors the user can fix (bad input, degenerate data) are :class:`StereoseedError`: printed as
one line ``stereoseed: error: ...`` with exit code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import sys
import warnings
from pathlib import Path

# One BLAS thread unless the user says otherwise, set before NumPy loads OpenBLAS: the pipeline's
# linear algebra is small matrices, where OpenBLAS's extra threads only spin against the
# feature thread and the dense workers (14-image box, whole command: 2.71 -> 2.50 s, CPU time
# 4.0 -> 2.5 s on 2 cores).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402 - after the BLAS setting

from stereoseed.cluster import CONNECT_TIMEOUT_S
from stereoseed.errors import StereoseedError
from stereoseed.geometry.models import MODELS


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


def _cmd_demo(args: argparse.Namespace) -> int:
    from stereoseed.experiments.demo import run_demo

    if args.images < 2:
        raise StereoseedError(f"--images {args.images}: the demo needs at least 2 images (the calibrated pair)")
    if not args.noise >= 0:
        raise StereoseedError(f"--noise {args.noise}: image noise is a standard deviation, >= 0")
    _say_if_compiling(quiet=False)
    return run_demo(Path(args.out), n_images=args.images, noise=args.noise, dense=not args.sparse, say=print)


def _cmd_precompile(args: argparse.Namespace) -> int:
    from stereoseed.precompile import precompile

    print(f"stereoseed: Numba kernels compiled and cached ({precompile():.0f} s)", file=sys.stderr)
    return 0


def _cmd_match(args: argparse.Namespace) -> int:
    from stereoseed.config import Config
    from stereoseed.features.harris import extract_features
    from stereoseed.io.files import check_image_output, read_image
    from stereoseed.matching.pair import match_pair
    from stereoseed.output.visualize import draw_matches

    if args.output:
        check_image_output(args.output)
    cfg = Config()
    img1, img2 = read_image(args.image1), read_image(args.image2)
    f1, f2 = extract_features(img1, cfg.features), extract_features(img2, cfg.features)
    for path, f in ((args.image1, f1), (args.image2, f2)):
        if len(f) == 0:
            print(f"stereoseed: warning: {path}: no interest points (a flat or empty image?); no matches",
                  file=sys.stderr)
    pair = match_pair(f1, f2, cfg.matching, image_width=img1.shape[1])
    matches, stats = pair.matches, pair.stats
    print(f"{len(f1.points)} / {len(f2.points)} interest points; "
          + ", ".join(f"{k}: {v}" for k, v in stats.items()))
    if args.output:
        draw_matches(img1, f1.points, img2, f2.points, matches, args.output)
        print(f"wrote {args.output}")
    return 0


def _cmd_propagate(args: argparse.Namespace) -> int:
    from stereoseed.geometry.projection import fundamental_from_projections
    from stereoseed.config import Config
    from stereoseed.io.files import check_image_output, read_calibration, read_image
    from stereoseed.sfm.mapper import initialise
    from stereoseed.matching.propagation.core import propagate
    from stereoseed.output.visualize import save_propagation_png

    if args.output:
        check_image_output(args.output)
    cfg = Config()
    names = [Path(args.image1).name, Path(args.image2).name]
    img1, img2 = read_image(args.image1), read_image(args.image2)
    P1, P2 = read_calibration(args.calib, names)
    # the pair as the reconstruction starts from it: a calibration that does not fit the images
    # is refused, and the seeds are its triangulated matches
    recon, _ = initialise([img1, img2], names, [P1, P2], cfg)
    seeds = recon.shared_pixels(0, 1)
    result = propagate(img1, img2, seeds, fundamental_from_projections(P1, P2), cfg.propagation,
                       subpixel_method=cfg.propagation.subpixel_method)
    print(f"{len(seeds)} seeds -> {result.n_matches} propagated matches in {result.timings.get('total', 0):.2f} s")
    if args.output:
        save_propagation_png(img1, result, args.output)
        print(f"wrote {args.output}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from stereoseed.experiments.paper import run_paper_bench

    run_paper_bench(Path(args.out), quick=args.quick, seed=args.seed)
    print(f"wrote {args.out}")
    return 0


EXIT_SKIPPED = 3  # --strict: every step worked but some image could not be placed
EXIT_SEQUENCES_FAILED = 1  # batch: some sequence could not be reconstructed (the others were)


def _config(args: argparse.Namespace):
    """The run's Config from the options reconstruct and batch share (:func:`_add_run_options`)."""
    from stereoseed.config import Config
    from stereoseed.sfm.config import PipelineConfig

    try:
        return Config(pipeline=PipelineConfig(mode=args.mode, camera_model=args.camera_model, window=args.window,
                                              ba=args.ba))
    except ValueError as e:
        raise StereoseedError(str(e)) from None


def _pool(args: argparse.Namespace, workers: int):
    """Where the jobs run: the Dask cluster of --scheduler (connected now, before any work),
    else local (None: the library's default)."""
    from contextlib import nullcontext

    from stereoseed.cluster import executor_for

    if args.scheduler is None:
        return nullcontext()
    return executor_for(args.scheduler, workers, connect_timeout=args.connect_timeout)


class _Bar:
    """The progress callback (done, total, message) as a tqdm bar on stderr, shown from the
    first report on: a run refused before any work leaves only its error line. ``after``: the
    bar of the stage before, closed (its time stopped) when this one starts."""

    def __init__(self, unit: str, quiet: bool, after: "_Bar | None" = None):
        self.unit, self.quiet, self.after, self.bar = unit, quiet, after, None

    def __call__(self, done: int, total: int, message: str) -> None:
        from tqdm import tqdm

        if self.bar is None:
            if self.after is not None:
                self.after.close()
            self.bar = tqdm(total=total, unit=self.unit, file=sys.stderr, disable=self.quiet)
        self.bar.total, self.bar.n = total, done
        self.bar.set_postfix_str(message[:40])

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "_Bar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _say_if_compiling(quiet: bool) -> None:
    """One line before a first run on this installation: it compiles the kernels first."""
    from stereoseed.precompile import kernels_cached

    if not quiet and kernels_cached() is False:
        print("stereoseed: first run on this installation: compiling the Numba kernels once (about a minute on "
              "two cores; `stereoseed precompile` does it ahead)", file=sys.stderr)


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from stereoseed.pipeline import reconstruct_to_folder

    cfg = _config(args)
    if args.scheduler and not args.dense:
        raise StereoseedError("--scheduler sends the dense stage's pair jobs to a Dask cluster; add --dense")
    _say_if_compiling(args.quiet)
    with (_pool(args, cfg.dense.pool_size()) as pool, _Bar("image", args.quiet) as progress,
          _Bar("pair", args.quiet, after=progress) as dense_progress):
        report = reconstruct_to_folder(args.images, args.calib, args.out, cfg, dense=args.dense, resume=args.resume,
                                       progress=progress, pool=pool, dense_progress=dense_progress)
    failed = [r for r in report["per_image"] if r.get("status") == "failed"]
    if report.get("resumed_images"):
        print(f"resumed after {len(report['resumed_images'])} images already placed")
    if report["final"].get("no_zoom"):
        print("no image zoomed: every camera keeps the calibrated intrinsics (report.json: final.no_zoom)")
    for r in failed:
        print(f"skipped: {r['reason']}")
    if "dense" in report:
        print(f"quasi-dense: {report['dense']['points']} points" + (f" ({report['dense']['note']})"
                                                                     if report["dense"].get("note") else ""))
    print(f"registered {report['registered']}/{report['images']} images ({len(failed)} skipped), "
          f"{report['points']} points, reprojection RMS {report['reprojection']['rms_px']:.3f} px; wrote {args.out}")
    return EXIT_SKIPPED if (args.strict and failed) else 0


def _cmd_batch(args: argparse.Namespace) -> int:
    from stereoseed.batch import read_sequence_list, run_batch

    cfg = _config(args)
    sequences = read_sequence_list(args.sequences, args.out_root)
    _say_if_compiling(args.quiet)
    with _pool(args, cfg.dense.pool_size()) as pool, _Bar("sequence", args.quiet) as progress:
        outcomes = run_batch(sequences, cfg, dense=args.dense, pool=pool, progress=progress)
    for o in outcomes:
        if o.ok:
            s = o.summary
            dense = f", {s['dense_points']} dense points" if "dense_points" in s else ""
            print(f"{o.sequence.name}: registered {s['registered']}/{s['images']} images ({s['skipped']} skipped), "
                  f"{s['points']} points{dense}; wrote {o.sequence.out}")
        else:
            print(f"{o.sequence.name}: failed: {o.reason}")
    failed = [o for o in outcomes if not o.ok]
    print(f"batch: {len(outcomes) - len(failed)} of {len(outcomes)} sequences reconstructed"
          + ("; failed: " + ", ".join(f"{o.sequence.name} ({o.reason})" for o in failed) if failed else ""))
    return EXIT_SEQUENCES_FAILED if failed else 0


def _cmd_export(args: argparse.Namespace) -> int:
    from stereoseed.output.export import write_bundler, write_colmap, write_nvm
    from stereoseed.output.results import load_result

    result = load_result(args.result)
    out = Path(args.out)
    if args.format == "colmap":
        warnings_ = write_colmap(result, out, binary=args.binary)
        written = [out / f"{n}.{'bin' if args.binary else 'txt'}" for n in ("cameras", "images", "points3D")]
    elif args.format == "nvm":
        warnings_ = write_nvm(result, out / "model.nvm")
        written = [out / "model.nvm"]
    else:
        warnings_ = write_bundler(result, out)
        written = [out / "bundle.out", out / "list.txt"]
    for w in warnings_:
        print(f"stereoseed: warning: {w}", file=sys.stderr)
    print(f"{len(result.registered)} cameras, {len(result.tracks['point_xyz'])} points; wrote "
          + ", ".join(str(p) for p in written))
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    import webbrowser

    page = Path(args.result) / "report.html"
    if not page.is_file():
        raise StereoseedError(f"{args.result}: no report.html; run stereoseed reconstruct --out {args.result} first")
    uri = page.resolve().as_uri()
    if args.print:
        print(uri)
    elif webbrowser.open(uri):
        print(f"opened {uri}")
    else:
        print(f"stereoseed: warning: no browser to open; open {uri}", file=sys.stderr)
    return 0


def _cmd_target(args: argparse.Namespace) -> int:
    from stereoseed.calibration.target import make_target

    path = make_target(Path(args.out), size=args.size, faces=args.faces)
    names = ", ".join(f"face_{k}.png" for k in range(args.faces))
    print(f"wrote {names} (print at 100 %), assembly.png and {path}")
    return 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("stereoseed")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """The options of a run, shared by reconstruct and batch."""
    p.add_argument("--mode", choices=["paper", "accurate"], default="accurate",
                   help="'paper': the paper's chain (2-view points, 11-DOF cameras, 3-image local BA); "
                        "'accurate': multi-view tracks, constrained camera, wider window (default)")
    p.add_argument("--camera-model", choices=list(MODELS), default=None,
                   help="moving camera model (default: free in paper mode, focal in accurate mode; "
                        "fixed: the lens did not zoom, every image keeps the calibrated second camera's intrinsics)")
    p.add_argument("--window", type=int, default=None, help="number of latest cameras the local BA frees")
    p.add_argument("--ba", choices=["local", "global", "final"], default=None,
                   help="local BA after each insertion, global BA after each insertion, or local + one final global BA "
                        "(default: local in paper mode, final in accurate mode)")
    p.add_argument("--dense", action="store_true", help="add the quasi-dense stage (dense.ply)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="run the jobs (reconstruct: the dense stage's image pairs; batch: the sequences) on the Dask "
                        "cluster of this scheduler (pip install 'stereoseed[cluster]'; the workers must see the same "
                        "paths); default: this machine")
    p.add_argument("--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, metavar="SECONDS",
                   help="give up on a --scheduler that has not answered by then (default: %(default)g)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, only errors on the terminal")
    p.add_argument("--verbose", action="store_true", help="also log what the library reports as it goes (each skipped image and why, the matcher's "
                        "pairs without a robust F)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stereoseed", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

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

    p = sub.add_parser("match", help="Harris + ZNCC matches between two images, drawn side by side")
    p.add_argument("image1")
    p.add_argument("image2")
    p.add_argument("-o", "--output", help="PNG to draw the matches into")
    p.set_defaults(func=_cmd_match)

    p = sub.add_parser("reconstruct", help="incremental reconstruction of an ordered image sequence")
    p.add_argument("images", nargs="+",
                   help="a folder (images in name order) or a text file listing image paths; or the two calibrated "
                        "photos then the video of the walk (keyframes picked from it), e.g. pair1.png pair2.png walk.mp4")
    p.add_argument("--calib", required=True, help="calib.json (only each camera's 'P' is needed), a Middlebury *_par.txt or a COLMAP "
                        "model folder (the pair's cameras looked up by image name)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    _add_run_options(p)
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run into the same --out from its checkpoint (same result as an "
                        "uninterrupted run)")
    p.add_argument("--strict", action="store_true",
                   help=f"exit with code {EXIT_SKIPPED} when any image could not be placed (the results are written)")
    p.set_defaults(func=_cmd_reconstruct)

    p = sub.add_parser("batch", help="reconstruct many sequences, one result folder each (locally, or on a Dask cluster)")
    p.add_argument("sequences", help="a text file, one line per sequence: IMAGES CALIB OUT (relative paths from the "
                                     "file's folder; # starts a comment; see docs/formats.md)")
    p.add_argument("--out-root", help="folder that relative OUT paths are resolved against (default: the list's folder)")
    _add_run_options(p)
    p.set_defaults(func=_cmd_batch)

    p = sub.add_parser("export", help="write a result folder as a COLMAP model (text or binary), NVM or Bundler file")
    p.add_argument("result", help="a folder written by stereoseed reconstruct --out")
    p.add_argument("--format", choices=["colmap", "nvm", "bundler"], default="colmap")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--binary", action="store_true", help="COLMAP's binary .bin files instead of .txt")
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("propagate", help="quasi-dense match propagation of one calibrated pair, drawn as a disparity map")
    p.add_argument("image1")
    p.add_argument("image2")
    p.add_argument("--calib", required=True, help="calib.json or Middlebury *_par.txt holding both images' cameras")
    p.add_argument("-o", "--output", help="PNG: image 1 beside the disparity-coloured matches")
    p.set_defaults(func=_cmd_propagate)

    p = sub.add_parser("bench", help="reproduce the paper's experiments (figures, JSON, Markdown)")
    p.add_argument("which", choices=["paper"])
    p.add_argument("--out", default="paper_bench", help="output folder (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="a reduced run (few half-size images, two seeds)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("demo", help="render the synthetic box scene, calibrate, reconstruct, report the error")
    p.add_argument("--out", default="demo_output", help="output folder (default: %(default)s)")
    p.add_argument("--images", type=int, default=14, help="number of images (default: %(default)s)")
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian image noise, grey levels (default: 0)")
    p.add_argument("--sparse", action="store_true", help="skip the dense stage")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("precompile", help="compile the Numba kernels once (make's install step does it), so the "
                                          "first run does not wait for them")
    p.set_defaults(func=_cmd_precompile)

    p = sub.add_parser("view", help="open a result folder's report.html in the default browser")
    p.add_argument("result", help="a result folder (stereoseed reconstruct --out RESULT)")
    p.add_argument("--print", action="store_true", help="only print the report's file URI (headless machines)")
    p.set_defaults(func=_cmd_view)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line for a user, not a source excerpt."""
    print(f"stereoseed: warning: {message}", file=sys.stderr if file is None else file)


def _configure_logging(args: argparse.Namespace) -> None:
    """The library logs; the terminal shows warnings, or every step with --verbose, or errors
    only with --quiet."""
    level = (logging.DEBUG if getattr(args, "verbose", False) else
             logging.ERROR if getattr(args, "quiet", False) else logging.WARNING)
    logger = logging.getLogger("stereoseed")
    logger.setLevel(level)
    for old in [h for h in logger.handlers if getattr(h, "_stereoseed", False)]:
        logger.removeHandler(old)  # main() may run several times in one process (tests, notebooks)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("stereoseed: %(levelname)s: %(message)s"))
    handler._stereoseed = True
    logger.addHandler(handler)


def _interrupt(signum, frame) -> None:
    """SIGTERM ends a run as Ctrl-C does: what is written stays consistent, --resume continues."""
    raise KeyboardInterrupt


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args)
    shown_before, warnings.showwarning = warnings.showwarning, _show_warning
    term_before = signal.signal(signal.SIGTERM, _interrupt) if _main_thread() else None
    try:
        return int(args.func(args) or 0)
    except StereoseedError as e:
        print(f"stereoseed: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        hint = "; run the same command with --resume to continue" if args.command == "reconstruct" else ""
        print(f"stereoseed: interrupted{hint}", file=sys.stderr)
        return 130
    except OSError as e:  # e.g. an output folder that cannot be created
        print(f"stereoseed: error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = shown_before  # main() is also called in-process (tests, notebooks)
        if term_before is not None:
            signal.signal(signal.SIGTERM, term_before)


def run() -> None:
    """The ``stereoseed`` command: :func:`main`, then exit. The garbage collector is frozen
    first: the interpreter's teardown frees module after module, and each collection it triggers
    would walk Numba's object graph again (0.6-0.7 s of a 5 s run on the 14-image box, after the
    last output was written). Not in :func:`main`, which tests and notebooks call in-process."""
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
