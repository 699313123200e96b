"""`stereoseed data fetch NAME` and `stereoseed data list`: the sample sets for a clone without
../shared (:mod:`stereoseed.io.sample_data`)."""
from __future__ import annotations

import argparse
import sys

from stereoseed.cli._terminal import say


def _cmd_fetch(args: argparse.Namespace) -> int:
    from stereoseed.io.sample_data import SETS, fetch, offline_mirror

    path = fetch(args.name, args.dir, progress=sys.stderr.isatty())
    mirrored = " (the offline mirror's copy: nothing downloaded)" if path.parent == offline_mirror() else ""
    say(f"{args.name}: {path}{mirrored}")
    say(f"cite: {SETS[args.name].cite}")
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    from stereoseed.io.sample_data import default_data_dir, offline_mirror, sample_status

    sets = sample_status(args.dir)
    width = max(len(s.name) for s in sets)
    for s in sets:
        where = str(s.where) if s.where else ("absent: stereoseed data fetch " + s.name if s.fetchable
                                              else "absent; not fetchable yet (no checksums recorded)")
        say(f"{s.name:<{width}}  {s.about}\n{'':<{width}}  {where}")
    say(f"(looked in the offline mirror {offline_mirror()} and in {args.dir or default_data_dir()})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the data subcommand (fetch, list)."""
    p = sub.add_parser("data", help="the sample sets (Middlebury, Strecha, ChArUco photos): fetch one, list them")
    data = p.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    f = data.add_parser("fetch", help="download a sample set (checked against recorded SHA-256s) in the layout the "
                                      "README, tests and benchmarks use; nothing is downloaded when $STEREOSEED_DATA "
                                      "or ../shared/data already holds it")
    f.add_argument("name", metavar="NAME", help="the set (stereoseed data list)")
    f.add_argument("--dir", help="the folder to put it in (default: the user's data folder, "
                                 "~/.local/share/stereoseed on Linux)")
    f.set_defaults(func=_cmd_fetch)
    ls = data.add_parser("list", help="every sample set and where it is")
    ls.add_argument("--dir", help="the folder fetch puts sets in, if not the default")
    ls.set_defaults(func=_cmd_list)
