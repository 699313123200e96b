"""`stereoseed export` and `view`: a result folder handed on."""
from __future__ import annotations

import argparse
from pathlib import Path

from stereoseed.cli._terminal import say, warn
from stereoseed.errors import StereoseedError
from stereoseed.io.outputs import refuse_input_as_output


def _cmd_export(args: argparse.Namespace) -> int:
    from stereoseed.output.export import colmap_files, write_bundler, write_colmap, write_nvm
    from stereoseed.output.reader import load_result

    if args.undistort and args.format != "colmap":
        raise StereoseedError(f"--undistort is for --format colmap (--format {args.format} "
                              + ("always writes undistorted images)" if args.format == "nerfstudio" else
                                 "has no images); leave it out"))
    if args.images and not (args.undistort or args.format == "nerfstudio"):
        raise StereoseedError("--images is read by --format colmap --undistort and --format nerfstudio only; leave it out")
    out = Path(args.out)
    # the result folder itself, a list of photos: what the export reads is never where it writes
    refuse_input_as_output(out, [args.result, *(args.images or [])], "give another --out")
    for name in _export_files():
        refuse_input_as_output(out / name, args.images or [], "give another --out")
    result = load_result(args.result)
    if args.format == "nerfstudio" or args.undistort:
        return _handoff(result, out, args)
    if args.format == "colmap":
        warnings_ = write_colmap(result, out, binary=args.binary, force=args.force)
        written = [out / name for name in colmap_files(args.binary)]
    elif args.format == "nvm":
        warnings_ = write_nvm(result, out / "model.nvm", force=args.force)
        written = [out / "model.nvm"]
    else:
        warnings_ = write_bundler(result, out, force=args.force)
        written = [out / "bundle.out", out / "list.txt"]
    for w in warnings_:
        warn(w)
    say(f"{len(result.registered)} cameras, {len(result.tracks['point_xyz'])} points; wrote "
          + ", ".join(str(p) for p in written))
    return 0


def _export_files() -> list[str]:
    """Every file an export writes at a fixed place in its folder (the hand-offs' images are
    checked by stereoseed.output.handoff against the photos they read)."""
    from stereoseed.output.export import colmap_files
    from stereoseed.output.handoff import NERFSTUDIO_PLY

    model = colmap_files(False) + colmap_files(True)
    return [*model, *(f"sparse/0/{n}" for n in model), "model.nvm", "bundle.out", "list.txt", "transforms.json",
            NERFSTUDIO_PLY]


def _handoff(result, out: Path, args: argparse.Namespace) -> int:
    """The hand-offs with images: COLMAP's undistorted workspace, nerfstudio's folder."""
    from stereoseed.output.export import colmap_files
    from stereoseed.output.handoff import (
        NERFSTUDIO_PLY,
        write_colmap_undistorted,
        write_nerfstudio,
    )

    if args.format == "nerfstudio":
        done = write_nerfstudio(result, out, args.images, force=args.force)
        files = [out / "transforms.json", out / NERFSTUDIO_PLY]
    else:
        done = write_colmap_undistorted(result, out, args.images, binary=args.binary, force=args.force)
        files = [out / "sparse" / "0" / name for name in colmap_files(args.binary)]
    for w in done.warnings:
        warn(w)
    how = "undistorted" if done.undistorted else "copied (no lens)"
    say(f"{done.images} images {how} into {out / 'images'}, {done.cameras} PINHOLE camera"
        f"{'s' if done.cameras != 1 else ''}, {done.points} points; wrote " + ", ".join(str(p) for p in files))
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    import webbrowser

    page = Path(args.result) / "report.html"
    if not page.is_file():
        raise StereoseedError(f"{args.result}: no report.html; run stereoseed reconstruct --out {args.result} first")
    uri = page.resolve().as_uri()
    if args.print:
        say(uri)
    elif webbrowser.open(uri):
        say(f"opened {uri}")
    else:
        warn(f"no browser to open; open {uri}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the export and view subcommands."""
    p = sub.add_parser("export", help="write a result folder as a COLMAP model (text or binary), NVM or Bundler file, "
                                      "or hand it to Gaussian-splatting (colmap --undistort) or nerfstudio")
    p.add_argument("result", help="a folder written by stereoseed reconstruct --out")
    p.add_argument("--format", choices=["colmap", "nvm", "bundler", "nerfstudio"], default="colmap",
                   help="nerfstudio: OUT/transforms.json, OUT/images/ (undistorted, PINHOLE) and the sparse cloud "
                        "OUT/sparse_pc.ply")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--binary", action="store_true", help="COLMAP's binary .bin files instead of .txt")
    p.add_argument("--undistort", action="store_true",
                   help="colmap: OUT/images/ (the photos undistorted) and OUT/sparse/0/ with PINHOLE cameras, as colmap "
                        "image_undistorter leaves them (what Gaussian-splatting trainers read)")
    p.add_argument("--images", nargs="+", metavar="SOURCE",
                   help="the photos the run read (folders, list files or images, as given to reconstruct), found by "
                        "name; for --undistort and --format nerfstudio. Default: those RESULT/inputs.json records "
                        "(a result written before it existed needs --images; a video's keyframes are read from "
                        "RESULT/keyframes)")
    p.add_argument("--force", action="store_true",
                   help="write into a folder that holds other files, beside them: a file of the export's names that "
                        "it did not write is refused, never replaced")
    p.set_defaults(func=_cmd_export)


    p = sub.add_parser("view", help="open a result folder's report.html in the default browser")
    p.add_argument("result", help="a result folder (stereoseed reconstruct --out RESULT)")
    p.add_argument("--print", action="store_true", help="only print the report's file URI (headless machines)")
    p.set_defaults(func=_cmd_view)
