"""`stereoseed match`, `propagate`, `bench` and `precompile`: the steps on their own, the paper's experiments, the kernels."""
from __future__ import annotations

import argparse
from pathlib import Path

from stereoseed.cli._terminal import complain, say, warn
from stereoseed.io.outputs import record_written_file, refuse_foreign_file, refuse_input_as_output


def _cmd_match(args: argparse.Namespace) -> int:
    from stereoseed.config import Config
    from stereoseed.features.harris import extract_features
    from stereoseed.io.files import check_image_output, read_image
    from stereoseed.matching.pair import match_pair
    from stereoseed.output.visualize import draw_matches

    if args.output:
        check_image_output(args.output)
        refuse_input_as_output(args.output, [args.image1, args.image2], "give another -o")
        refuse_foreign_file(args.output, "give another -o")
    cfg = Config()
    img1, img2 = read_image(args.image1), read_image(args.image2)
    f1, f2 = extract_features(img1, cfg.features), extract_features(img2, cfg.features)
    for path, f in ((args.image1, f1), (args.image2, f2)):
        if len(f) == 0:
            warn(f"{path}: no interest points (a flat or empty image?); no matches")
    pair = match_pair(f1, f2, cfg.matching, image_width=img1.shape[1])
    matches, stats = pair.matches, pair.stats
    say(f"{len(f1.points)} / {len(f2.points)} interest points; "
          + ", ".join(f"{k}: {v}" for k, v in stats.items()))
    if args.output:
        draw_matches(img1, f1.points, img2, f2.points, matches, args.output)
        record_written_file(args.output)
        say(f"wrote {args.output}")
    return 0

def _cmd_propagate(args: argparse.Namespace) -> int:
    from stereoseed.config import Config
    from stereoseed.geometry.projection import fundamental_from_projections
    from stereoseed.io.files import check_image_output, read_calibration, read_image
    from stereoseed.matching.propagation.core import propagate
    from stereoseed.output.visualize import save_propagation_png
    from stereoseed.sfm.mapper import initialise

    if args.output:
        check_image_output(args.output)
        refuse_input_as_output(args.output, [args.image1, args.image2, args.calib], "give another -o")
        refuse_foreign_file(args.output, "give another -o")
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
    say(f"{len(seeds)} seeds -> {result.n_matches} propagated matches in {result.timings.get('total', 0):.2f} s")
    if args.output:
        save_propagation_png(img1, result, args.output)
        record_written_file(args.output)
        say(f"wrote {args.output}")
    return 0

def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib.util

    from stereoseed.errors import StereoseedError
    from stereoseed.experiments.paper import run_paper_bench

    if importlib.util.find_spec("matplotlib") is None:  # an extra: only the paper's figures need it
        raise StereoseedError("stereoseed bench paper draws its figures with matplotlib; install it with "
                              "pip install 'stereoseed[bench]'")
    run_paper_bench(Path(args.out), quick=args.quick, seed=args.seed)
    say(f"wrote {args.out}")
    return 0


def _cmd_precompile(args: argparse.Namespace) -> int:
    from stereoseed.precompile import precompile

    complain(f"stereoseed: Numba kernels compiled and cached ({precompile():.0f} s)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the match, propagate, bench, precompile subcommands."""
    p = sub.add_parser("match", help="Harris + ZNCC matches between two images, drawn side by side")
    p.add_argument("image1")
    p.add_argument("image2")
    p.add_argument("-o", "--output", help="PNG to draw the matches into")
    p.set_defaults(func=_cmd_match)


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


    p = sub.add_parser("precompile", help="compile the Numba kernels once (make's install step does it), so the "
                                          "first run does not wait for them")
    p.set_defaults(func=_cmd_precompile)

