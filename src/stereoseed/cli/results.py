"""`stereoseed export` and `view`: a result folder handed on."""
from __future__ import annotations

import argparse
from pathlib import Path

from stereoseed.cli._terminal import say, warn
from stereoseed.errors import StereoseedError


def _cmd_export(args: argparse.Namespace) -> int:
    from stereoseed.output.export import write_bundler, write_colmap, write_nvm
    from stereoseed.output.reader import load_result

    result = load_result(args.result)
    out = Path(args.out)
    if args.format == "colmap":
        warnings_ = write_colmap(result, out, binary=args.binary, force=args.force)
        written = [out / f"{n}.{'bin' if args.binary else 'txt'}" for n in ("cameras", "images", "points3D")]
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
    p = sub.add_parser("export", help="write a result folder as a COLMAP model (text or binary), NVM or Bundler file")
    p.add_argument("result", help="a folder written by stereoseed reconstruct --out")
    p.add_argument("--format", choices=["colmap", "nvm", "bundler"], default="colmap")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--binary", action="store_true", help="COLMAP's binary .bin files instead of .txt")
    p.add_argument("--force", action="store_true",
                   help="write into a folder that holds other files (files of the export's names are replaced)")
    p.set_defaults(func=_cmd_export)


    p = sub.add_parser("view", help="open a result folder's report.html in the default browser")
    p.add_argument("result", help="a result folder (stereoseed reconstruct --out RESULT)")
    p.add_argument("--print", action="store_true", help="only print the report's file URI (headless machines)")
    p.set_defaults(func=_cmd_view)
