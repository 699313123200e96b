"""`stereoseed mesh`: a result folder's quasi-dense cloud as a trimmed, coloured surface."""
from __future__ import annotations

import argparse

from stereoseed.cli._terminal import say
from stereoseed.cli.arguments import whole_number


def _cmd_mesh(args: argparse.Namespace) -> int:
    from stereoseed.dense.mesh import MeshConfig, mesh_result

    path, summary = mesh_result(args.result, args.out, MeshConfig(depth=args.depth))
    normals = "its normals" if summary["normals"] == "dense.ply" else "normals estimated towards the cameras"
    say(f"mesh: {summary['faces']} faces, {summary['vertices']} vertices from {summary['points']} points, "
        f"depth {summary['depth']} "
        f"({normals}; {summary['poisson_faces'] - summary['faces']} Poisson faces beyond the cloud trimmed) "
        f"in {summary['seconds']:.1f} s; wrote {path}" + ("; report.html shows it" if summary.get("report_html") else ""))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the mesh subcommand."""
    p = sub.add_parser("mesh", help="screened Poisson surface of a result's dense.ply, trimmed to the cloud, with "
                                    "its colours (needs the extra: pip install 'stereoseed[mesh]')")
    p.add_argument("result", help="a folder written by stereoseed reconstruct --dense --out RESULT")
    p.add_argument("--out", help="the mesh's PLY file (default: RESULT/mesh.ply, listed with the result's files)")
    p.add_argument("--depth", type=_depth, default=8,
                   help="Poisson octree depth, 4..12: each level halves the grid cell (finer detail, about 4x the "
                        "time), or auto: from the cloud's point spacing (curved objects; docs/dense.md); "
                        "default: %(default)s")
    p.add_argument("--verbose", action="store_true", help="log each step")
    p.set_defaults(func=_cmd_mesh)


# Poisson's octree depth; "auto": MeshConfig's depth from the point spacing (0)
_depth = whole_number(4, 12, words={"auto": 0}, note="from the point spacing")