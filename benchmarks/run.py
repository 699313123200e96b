"""`make bench`: every benchmark of the project, one JSON file. Figures live here, never in tests.

    python benchmarks/run.py --out bench_output [--only matching,propagation,...]
"""
from __future__ import annotations

import os

# one BLAS thread, set before NumPy loads OpenBLAS: the sections measure what the command line runs
# (stereoseed.cli sets the same)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

SECTIONS = ["speed", "calibration", "lens", "matching", "reconstruction", "propagation", "dense", "dense_real", "real", "walks", "realcal", "mesh", "rig", "firstrun", "stability", "ordering", "live"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench_output")
    parser.add_argument("--only", default=",".join(SECTIONS), help="comma-separated sections")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"machine": {"python": platform.python_version(), "platform": platform.platform()}}
    from stereoseed.io.files import write_json

    for name in args.only.split(","):
        module = importlib.import_module(f"bench_{name}")
        t = time.perf_counter()
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        results[name] = module.run()
        results[name]["bench_seconds"] = time.perf_counter() - t
        write_json(out / "bench.json", results)  # keep what is done if a later section fails
        print(json.dumps({name: results[name]}, indent=1)[:4000])
    print(f"wrote {out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
