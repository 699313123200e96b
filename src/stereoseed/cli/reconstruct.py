"""`stereoseed reconstruct`, `batch` and `demo`: the runs."""
from __future__ import annotations

import argparse
from pathlib import Path

from stereoseed.cli._progress import Bar, say_if_compiling
from stereoseed.cli._terminal import say
from stereoseed.cluster import CONNECT_TIMEOUT_S
from stereoseed.errors import StereoseedError
from stereoseed.geometry.camera_model import MODELS

EXIT_SKIPPED = 3  # --strict: every step worked but some image could not be placed, or was flagged

EXIT_SEQUENCES_FAILED = 1  # batch: some sequence could not be reconstructed (the others were)

def _config(args: argparse.Namespace):
    """The run's Config: the --config file's (a TOML file, or a run's report.json replayed), then
    the options given on the command line over it, field by field (:func:`_add_config_options`)."""
    from stereoseed.config import Config

    cfg = Config.from_file(args.config) if args.config else Config()
    try:
        if args.mode is not None and args.mode != cfg.pipeline.mode:
            cfg = cfg.with_mode(args.mode)  # what the file held at its mode's defaults follows the new mode
        given = {"camera_model": args.camera_model, "window": args.window, "ba": args.ba}
        changes = {"pipeline": {k: v for k, v in given.items() if v is not None}}
        if args.keep_flagged:
            changes["trust"] = {"keep_flagged": True}
        if getattr(args, "refine_rig", False):
            changes["pipeline"]["refine_rig"] = True
        if getattr(args, "order", None) is not None:
            changes["ordering"] = {"mode": args.order}
        dense = {"min_support": getattr(args, "min_support", None), "resolution": getattr(args, "dense_resolution", None),
                 "max_points": getattr(args, "max_points", None)}
        if any(v is not None for v in dense.values()):
            changes["dense"] = {k: v for k, v in dense.items() if v is not None}
        return cfg.replace(**changes)
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

def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from stereoseed.pipeline import reconstruct_to_folder  # its report: the folder is not read back
    from stereoseed.scene.camera_life import flag_kind

    cfg = _config(args)
    if args.scheduler and not args.dense:
        raise StereoseedError("--scheduler sends the dense stage's pair jobs to a Dask cluster; add --dense")
    images, right = args.images, None
    if args.rig:
        if len(args.images) != 2:
            raise StereoseedError(f"--rig takes two image sources, the left camera's then the right one's (a folder, "
                                  f"a list file or a video each); got {len(args.images)}")
        images, right = args.images
    say_if_compiling("dense" if args.dense else "sparse")
    with (_pool(args, cfg.dense.pool_size()) as pool, Bar("image", args.quiet) as progress,
          Bar("pair", args.quiet, after=progress) as dense_progress):
        report = reconstruct_to_folder(images, args.calib, args.out, cfg, dense=args.dense, resume=args.resume,
                                       progress=progress, pool=pool, dense_progress=dense_progress, rig_right=right,
                                       mesh=args.mesh, unit=args.unit)
    failed = [r for r in report["per_image"] if r.get("status") == "failed"]
    if report.get("resumed_images"):
        say(f"resumed after {len(report['resumed_images'])} images already placed")
    if report["final"].get("no_zoom"):
        say("no image zoomed: every camera keeps the calibrated intrinsics (report.json: final.no_zoom)")
    for r in failed:
        say(f"skipped: {r['reason']}")
    # each flagged image's reason was logged (stderr) when it was flagged; the summary line names them
    flagged = (report["final"].get("trust") or {}).get("flagged") or {}
    loop = report["final"].get("loop_closure") or {}
    if loop:
        from stereoseed.output.report.measure import length_text
        from stereoseed.sfm.loop_closure import describe_loop

        say(f"loop closure: {describe_loop(loop, lambda x: length_text(x, report.get('unit')))}")
    if "mesh" in report:
        say(f"mesh: {report['mesh'].get('faces')} faces ({Path(args.out) / 'mesh.ply'}, shown in report.html)")
    if "dense" in report:
        say(f"quasi-dense: {report['dense']['points']} points" + (f" ({report['dense']['note']})"
                                                                     if report["dense"].get("note") else ""))
    flags = f", {len(flagged)} flagged: " + ", ".join(f"{n} {flag_kind(r)}" for n, r in flagged.items()) \
        if flagged else ", 0 flagged"
    far = report.get("far_points_dropped") or 0
    points = f"{report.get('exported_points', report['points'])} points" + (
        f" ({far} far point{'s' if far > 1 else ''} left out)" if far else "")
    say(f"registered {report['registered']}/{report['images']} images ({len(failed)} skipped{flags}), "
        f"{points}, reprojection RMS {report['reprojection']['rms_px']:.3f} px; wrote {args.out}")
    return EXIT_SKIPPED if (args.strict and (failed or flagged)) else 0

def _cmd_batch(args: argparse.Namespace) -> int:
    from stereoseed.batch import read_sequence_list, run_batch

    cfg = _config(args)
    sequences = read_sequence_list(args.sequences, args.out_root, allow_outside=args.allow_outside)
    say_if_compiling("dense" if args.dense else "sparse")
    with _pool(args, cfg.dense.pool_size()) as pool, Bar("sequence", args.quiet) as progress:
        outcomes = run_batch(sequences, cfg, dense=args.dense, pool=pool, progress=progress)
    for o in outcomes:
        if o.ok:
            s = o.summary
            dense = f", {s['dense_points']} dense points" if "dense_points" in s else ""
            say(f"{o.sequence.name}: registered {s['registered']}/{s['images']} images ({s['skipped']} skipped), "
                  f"{s['points']} points{dense}; wrote {o.sequence.out}")
        else:
            say(f"{o.sequence.name}: failed: {o.reason}")
    failed = [o for o in outcomes if not o.ok]
    say(f"batch: {len(outcomes) - len(failed)} of {len(outcomes)} sequences reconstructed"
          + ("; failed: " + ", ".join(f"{o.sequence.name} ({o.reason})" for o in failed) if failed else ""))
    return EXIT_SEQUENCES_FAILED if failed else 0

def _cmd_demo(args: argparse.Namespace) -> int:
    from stereoseed.experiments.demo import run_demo

    if args.images < 2:
        raise StereoseedError(f"--images {args.images}: the demo needs at least 2 images (the calibrated pair)")
    if not args.noise >= 0:
        raise StereoseedError(f"--noise {args.noise}: image noise is a standard deviation, >= 0")
    from stereoseed.config import Config

    cfg = Config.from_file(args.config) if args.config else None
    say_if_compiling(run="demo-sparse" if args.sparse else "demo")
    return run_demo(Path(args.out), n_images=args.images, noise=args.noise, dense=not args.sparse, say=say, cfg=cfg)

def _cmd_config(args: argparse.Namespace) -> int:
    say(_config(args).to_toml().rstrip("\n"))
    return 0


def _add_config_options(p: argparse.ArgumentParser) -> None:
    """The options that set the run's Config: a file, then single fields over it."""
    p.add_argument("--config", metavar="FILE",
                   help="the settings: a TOML file with a table per section of Config (docs/config.md), or a run's "
                        "report.json to run again with its configuration; the options below override it")
    p.add_argument("--mode", choices=["paper", "accurate"], default=None,
                   help="'paper': the paper's chain (2-view points, 11-DOF cameras, 3-image local BA); "
                        "'accurate': multi-view tracks, constrained camera, wider window (default)")
    p.add_argument("--camera-model", choices=list(MODELS), default=None,
                   help="moving camera model (default: free in paper mode, focal in accurate mode; "
                        "fixed: the lens did not zoom, every image keeps the calibrated second camera's intrinsics)")
    p.add_argument("--window", type=int, default=None, help="number of latest cameras the local BA frees")
    p.add_argument("--ba", choices=["local", "global", "final"], default=None,
                   help="local BA after each insertion, global BA after each insertion, or local + one final global BA "
                        "(default: local in paper mode, final in accurate mode)")
    p.add_argument("--keep-flagged", action="store_true",
                   help="keep the observations of cameras the run flagged (reliable false in cameras.json) in the model "
                        "and their images in the dense stage (default: no point or dense match rests on them)")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """The options of a run, shared by reconstruct and batch."""
    _add_config_options(p)
    p.add_argument("--dense", action="store_true", help="add the quasi-dense stage (dense.ply)")
    p.add_argument("--min-support", type=int, default=None, metavar="VIEWS",
                   help="keep a dense point other views can judge only when this many views agree on it, its pair's "
                        "two included (default: 3, one other pair confirms it; 2: no check); dense.ply gives each "
                        "point's support, angle and confidence (docs/dense.md)")
    p.add_argument("--dense-resolution", type=int, default=None, metavar="PX",
                   help="propagate on images whose longer side is at most PX pixels (default: the images' own "
                        "size); bounds the dense stage's memory and time on large photos")
    p.add_argument("--max-points", type=int, default=None, metavar="N",
                   help="at most N points in dense.ply: the fusion voxel grown until the cloud fits (default: no "
                        "limit, one point per pixel's footprint)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="run the jobs (reconstruct: the dense stage's image pairs; batch: the sequences) on the Dask "
                        "cluster of this scheduler (pip install 'stereoseed[cluster]'; the workers must see the same "
                        "paths); default: this machine")
    p.add_argument("--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, metavar="SECONDS",
                   help="give up on a --scheduler that has not answered by then (default: %(default)g)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, only errors on the terminal")
    p.add_argument("--verbose", action="store_true", help="also log what the library reports as it goes (each skipped image and why, the matcher's "
                        "pairs without a robust F)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the reconstruct, batch and demo subcommands."""
    p = sub.add_parser("reconstruct", help="incremental reconstruction of an ordered image sequence")
    p.add_argument("images", nargs="+",
                   help="a folder (images in name order) or a text file listing image paths; or the two calibrated "
                        "photos then the video of the walk (keyframes picked from it), e.g. pair1.png pair2.png walk.mp4")
    p.add_argument("--calib", required=True, help="calib.json (only each camera's 'P' is needed), a Middlebury *_par.txt or a COLMAP "
                        "model folder (the pair's cameras looked up by image name)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--unit", metavar="NAME", help="the calibration's unit where it names none (a par file, a COLMAP "
                   "model; calib.json's \"unit\" otherwise), such as m: report.html's lengths are in it")
    p.add_argument("--refine-rig", action="store_true",
                   help="with --rig: refine the rig's relative pose once in the final bundle adjustment (rotation and "
                        "baseline direction; the baseline length keeps the scale); default: held as calibrated")
    p.add_argument("--mesh", action="store_true",
                   help="also mesh the dense cloud into mesh.ply (with --dense; pip install 'stereoseed[mesh]')")
    p.add_argument("--rig", action="store_true",
                   help="a stereo rig walked with both cameras: IMAGES is the left camera's folder (or list, or video) "
                        "then the right camera's, image (frame) k of each taken together; the calibrated pair is the "
                        "first station")
    _add_run_options(p)
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run into the same --out from its checkpoint (same result as an "
                        "uninterrupted run)")
    p.add_argument("--strict", action="store_true",
                   help=f"exit with code {EXIT_SKIPPED} when any image could not be placed or was flagged (the results "
                        f"are written)")
    p.add_argument("--order", choices=["auto", "images", "as-given"], default=None,
                   help="auto (default): a folder's photos are run in the walk order their overlaps give, the first "
                        "two staying the calibrated pair (a list file as written); images: a list's too; as-given: "
                        "never reordered")
    p.set_defaults(func=_cmd_reconstruct)


    p = sub.add_parser("batch", help="reconstruct many sequences, one result folder each (locally, or on a Dask cluster)")
    p.add_argument("sequences", help="a text file, one line per sequence: IMAGES CALIB OUT (relative paths from the "
                                     "file's folder; # starts a comment; see docs/formats.md)")
    p.add_argument("--out-root", help="folder that relative OUT paths are resolved against (default: the list's folder)")
    p.add_argument("--allow-outside", action="store_true",
                   help="let an OUT lie outside --out-root (an absolute path, or one climbing out with ..)")
    _add_run_options(p)
    p.set_defaults(func=_cmd_batch)


    p = sub.add_parser("demo", help="render the synthetic box scene, calibrate, reconstruct, report the error")
    p.add_argument("--out", default="demo_output", help="output folder (default: %(default)s)")
    p.add_argument("--images", type=int, default=14, help="number of images (default: %(default)s)")
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian image noise, grey levels (default: 0)")
    p.add_argument("--sparse", action="store_true", help="skip the dense stage")
    p.add_argument("--config", metavar="FILE", help="the run's settings: a TOML file (docs/config.md) or a result's "
                                                   "report.json")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("config", help="print the configuration a run would use, resolved, as TOML (every field: "
                                      "a starting point for --config)")
    _add_config_options(p)
    p.set_defaults(func=_cmd_config)

