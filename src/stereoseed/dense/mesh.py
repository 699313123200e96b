"""A surface from the quasi-dense cloud: screened Poisson reconstruction (Kazhdan & Hoppe 2013,
through PyMeshLab, the optional extra ``mesh``), trimmed to where the cloud is, coloured from it.

The octree's depth is fixed (``MeshConfig.depth``) or, with depth 0, follows the cloud's point
spacing (a grid cell of a few spacings: the mesh keeps the cloud's accuracy on curved surfaces
too, at some of the box's completeness: docs/dense.md); each point weighs in the fit
by its confidence (dense.ply's), and points below ``MeshConfig.min_confidence`` are left out.

Poisson fits a closed implicit surface to oriented points, so it also makes surface where there
are none (it closes an open ground plane with a bubble underneath, bridges the gaps). The mesh is
therefore trimmed: a vertex farther than ``max_gap_cells`` Poisson cells from every cloud point,
or whose Poisson density (the octree depth its samples call for, PoissonRecon's measure of the
sampling density: one unit more is four times the points per area) is more than
``density_drop`` below the typical density of the surface the cloud covers, is dropped with
its faces. Each kept vertex takes the mean colour of its nearest cloud points.

:func:`poisson_mesh` is arrays in, :class:`Mesh` out; :func:`write_mesh` writes it as a PLY;
:func:`mesh_result` does both for a result folder's ``dense.ply``.
"""
from __future__ import annotations

import logging
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.dense.config import MeshConfig
from stereoseed.errors import StereoseedError
from stereoseed.io.outputs import same_file
from stereoseed.io.ply import read_dense_ply, write_ply

__all__ = ["MESH_NAME", "Mesh", "MeshConfig", "camera_viewpoints", "mesh_result", "point_spacing", "poisson_depth",
           "poisson_mesh", "write_mesh"]

log = logging.getLogger(__name__)

MESH_NAME = "mesh.ply"  # the mesh's name in the result folder when no other is given
INSTALL_HINT = "pip install 'stereoseed[mesh]'"
_OUR_COMMENT = b"comment written by stereoseed"  # what io.ply writes in every header


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: vertices (V, 3) float64, faces (F, 3) int64 (counter-clockwise seen from
    outside, where the normals point), colors (V, 3) uint8 RGB, normals (V, 3) unit vectors,
    density (V,) Poisson's sampling density at each vertex."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    density: np.ndarray

    def area(self) -> float:
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def require_meshing() -> None:
    """Raise :class:`StereoseedError` (how to install it) unless the mesh extra is installed:
    a run that ends with a mesh checks it before any work."""
    _pymeshlab()


def _pymeshlab() -> Any:
    # PyMeshLab loads its own (older) TBB; Numba then says, on its next parallel kernel, that it
    # cannot use TBB and takes its OpenMP layer: nothing the user can act on
    warnings.filterwarnings("ignore", message="The TBB threading layer requires")
    try:
        import pymeshlab
    except ImportError:
        raise StereoseedError(f"meshing needs PyMeshLab, which is not installed: {INSTALL_HINT}") from None
    return pymeshlab


SPACING_SAMPLE = 20_000  # points whose nearest neighbour measures the spacing: its median is stable to ~1 %


def point_spacing(points: np.ndarray, tree: Any = None) -> float:
    """The cloud's point spacing: the median distance of a point (N, 3) to its nearest other
    point (over a fixed random sample of SPACING_SAMPLE points when there are more)."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    sample = points
    if len(points) > SPACING_SAMPLE:
        sample = points[np.random.default_rng(0).choice(len(points), SPACING_SAMPLE, replace=False)]
    distance, _ = tree.query(sample, k=2)
    return float(np.median(distance[:, 1]))


def poisson_depth(points: np.ndarray, cfg: MeshConfig, spacing: float) -> int:
    """The octree depth: ``cfg.depth``, or (0) the shallowest whose grid cell is at most
    ``cfg.cell_spacings`` point spacings, within the configured bounds."""
    if cfg.depth:
        return cfg.depth
    extent = cfg.scale * float(np.max(points.max(axis=0) - points.min(axis=0)))
    if not spacing > 0:  # every point doubled: no spacing to read
        return cfg.min_auto_depth
    wanted = int(np.ceil(np.log2(extent / (cfg.cell_spacings * spacing))))
    depth = min(max(wanted, cfg.min_auto_depth), cfg.max_auto_depth)
    if depth < wanted:
        log.warning("mesh: the cloud's spacing (%.3g) calls for Poisson depth %d; depth %d (MeshConfig.max_auto_depth) "
                    "is used, the mesh is smoother than the cloud", spacing, wanted, depth)
    return depth


def poisson_mesh(points: np.ndarray, normals: np.ndarray, colors: np.ndarray,
                 cfg: MeshConfig = MeshConfig(), confidence: np.ndarray | None = None) -> tuple[Mesh, dict[str, Any]]:
    """Screened Poisson surface of an oriented cloud, trimmed to the cloud, coloured from it.

    points (N, 3), normals (N, 3) unit vectors towards the outside (where the cameras were),
    colors (N, 3) uint8 RGB; confidence (N,) in (0, 1] (dense.ply's), when given: each point's
    weight in the Poisson fit (PoissonRecon's confidence: its normal scaled by it), and points
    below ``cfg.min_confidence`` left out. The octree depth: :func:`poisson_depth`. Returns the
    mesh and a summary (counts before and after each trim, the depth, the grid cell, the point
    spacing, seconds). Raises :class:`StereoseedError` for too few points, a cloud without finite
    coordinates, or when the extra is missing."""
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    normals = np.ascontiguousarray(normals, np.float64).reshape(-1, 3)
    colors = np.asarray(colors).reshape(-1, 3)
    if not len(points) == len(normals) == len(colors):
        raise ValueError(f"points, normals and colors differ in length ({len(points)}, {len(normals)}, {len(colors)})")
    good = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(normals), axis=1)
    if confidence is not None:
        confidence = np.asarray(confidence, np.float64).reshape(-1)
        if len(confidence) != len(points):
            raise ValueError(f"confidence has {len(confidence)} values for {len(points)} points")
        good &= np.isfinite(confidence) & (confidence >= cfg.min_confidence)
        confidence = confidence[good]
    points, normals, colors = points[good], normals[good], colors[good]
    if len(points) < cfg.min_points:
        raise StereoseedError(f"the cloud has {len(points)} usable points, fewer than the {cfg.min_points} a mesh "
                              f"needs; reconstruct with more images or --dense on a textured object")
    tree = cKDTree(points)
    spacing = point_spacing(points, tree)
    depth = poisson_depth(points, cfg, spacing)
    vertices, faces, vertex_normals, density = _screened_poisson(points, normals, confidence, depth, cfg)
    cell = cfg.scale * float(np.max(points.max(axis=0) - points.min(axis=0))) / 2 ** depth
    gap, _ = tree.query(vertices, workers=cfg.pool_size())
    near = gap <= cfg.max_gap_cells * cell
    reference = float(np.median(density[near])) if near.any() else float("nan")
    dense_enough = density >= reference - cfg.density_drop
    keep = near & dense_enough
    mesh = _submesh(vertices, faces, vertex_normals, density, keep)
    k = min(cfg.color_neighbours, len(points))
    _, idx = tree.query(mesh.vertices, k=k, workers=cfg.pool_size())
    idx = idx.reshape(len(mesh.vertices), k)
    mean = colors[idx].astype(np.float64).mean(axis=1) if len(idx) else np.zeros((0, 3))
    mesh = Mesh(mesh.vertices, mesh.faces, np.rint(mean).astype(np.uint8), mesh.normals, mesh.density)
    summary = {"points": int(len(points)), "depth": depth, "cell": cell, "spacing": spacing,
               "weighted_by_confidence": confidence is not None,
               "poisson_vertices": int(len(vertices)), "poisson_faces": int(len(faces)),
               "dropped_far_from_cloud": int((~near).sum()), "dropped_low_density": int((near & ~dense_enough).sum()),
               "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)), "area": mesh.area(),
               "seconds": time.perf_counter() - t0}
    log.info("mesh: %d faces (%d before trimming) from %d points, depth %d, grid cell %.3g (point spacing %.3g)",
             summary["faces"], summary["poisson_faces"], summary["points"], depth, cell, spacing)
    return mesh, summary


def _screened_poisson(points: np.ndarray, normals: np.ndarray, confidence: np.ndarray | None, depth: int,
                      cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PyMeshLab's screened Poisson: vertices, faces, vertex normals, density (its vertex
    quality). confidence: the points' weights (their quality, PyMeshLab's confidence flag)."""
    pymeshlab = _pymeshlab()
    meshes = pymeshlab.MeshSet()
    if confidence is None:
        meshes.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    else:
        meshes.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals, v_scalar_array=confidence))
    meshes.generate_surface_reconstruction_screened_poisson(
        depth=depth, scale=cfg.scale, samplespernode=cfg.samples_per_node, pointweight=cfg.point_weight,
        confidence=confidence is not None, preclean=False, threads=cfg.pool_size())
    out = meshes.current_mesh()
    if out.face_number() == 0 or not out.has_vertex_scalar():
        raise StereoseedError("screened Poisson made no surface of the cloud (all its points on a line or a "
                              "point?); check dense.ply in a viewer")
    vertices = np.asarray(out.vertex_matrix(), np.float64)
    faces = np.asarray(out.face_matrix(), np.int64)
    vn = np.asarray(out.vertex_normal_matrix(), np.float64)
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    return vertices, faces, vn / np.where(length > 0, length, 1.0), np.asarray(out.vertex_scalar_array(), np.float64)


def _submesh(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, density: np.ndarray,
             keep: np.ndarray) -> Mesh:
    """The faces whose three vertices are kept, and the vertices they use, renumbered."""
    faces = faces[keep[faces].all(axis=1)]
    used = np.zeros(len(vertices), bool)
    used[faces.reshape(-1)] = True
    number = np.cumsum(used) - 1
    return Mesh(vertices[used], number[faces], np.zeros((int(used.sum()), 3), np.uint8), normals[used],
                density[used])


def camera_viewpoints(points: np.ndarray, projections: list[np.ndarray], sizes: list[tuple[int, int]]) -> np.ndarray:
    """Where each point (N, 3) was seen from (N, 3): the centre of the nearest camera that has it
    in front and inside its image (P (3, 4), (width, height) each); a point no camera frames
    takes the nearest centre. With :func:`stereoseed.dense.normals.estimate_normals` it turns
    estimated normals to the outside, where the cameras stood."""
    from stereoseed.geometry.projection import camera_center

    points = np.asarray(points, np.float64).reshape(-1, 3)
    if not projections:
        raise ValueError("camera_viewpoints needs at least one camera")
    centres = np.array([camera_center(P) for P in projections])
    best = np.full(len(points), np.inf)
    nearest_any = np.full(len(points), np.inf)
    view = np.zeros(len(points), np.int64)
    fallback = np.zeros(len(points), np.int64)
    homogeneous = np.c_[points, np.ones(len(points))]
    for c, (P, (w, h)) in enumerate(zip(projections, sizes)):
        x = homogeneous @ np.asarray(P, np.float64).T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
        # in front: the depth's sign with P's own (a P scaled by -1 is the same camera)
        depth = x[:, 2] * np.sign(np.linalg.det(np.asarray(P, np.float64)[:, :3]))
        framed = (depth > 0) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        distance = np.linalg.norm(points - centres[c], axis=1)
        closer = framed & (distance < best)
        best[closer], view[closer] = distance[closer], c
        closer_any = distance < nearest_any
        nearest_any[closer_any], fallback[closer_any] = distance[closer_any], c
    return centres[np.where(np.isfinite(best), view, fallback)]


def _is_our_mesh(path: Path) -> bool:
    """Whether ``path`` is a mesh this module wrote: a plain file (not a link) with stereoseed's
    PLY header, a face element and the vertex density (sparse.ply, dense.ply and cameras.ply are
    not meshes of this kind)."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    header = head.split(b"end_header", 1)[0]
    return (head.startswith(b"ply") and _OUR_COMMENT in header and b"element face" in header
            and b"property float density" in header)


def _refuse_foreign(path: Path) -> None:
    """Refuse to write over anything at ``path`` but a mesh stereoseed wrote."""
    if (path.exists() or path.is_symlink()) and not _is_our_mesh(path):
        raise StereoseedError(f"{path}: exists and is not a mesh stereoseed wrote; give another --out or move it away")


def write_mesh(path: str | os.PathLike, mesh: Mesh) -> Path:
    """The mesh as a binary PLY (x y z, colour, normal, density per vertex; triangles),
    atomically. An existing file is replaced only when it is a mesh stereoseed wrote; anything
    else there (the user's file, another result file, a folder) is refused, untouched."""
    path = Path(path)
    _refuse_foreign(path)
    properties = {"nx": mesh.normals[:, 0].astype(np.float32), "ny": mesh.normals[:, 1].astype(np.float32),
                  "nz": mesh.normals[:, 2].astype(np.float32), "density": mesh.density.astype(np.float32)}
    return write_ply(path, mesh.vertices, mesh.colors, properties, faces=mesh.faces)


def _read_cloud(folder: Path, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str]:
    """Points, normals, colours and confidence (None when the file has none) of the folder's
    dense.ply, and where the normals come from: the file's, or estimated and turned towards the
    cameras of cameras.json that frame each point."""
    points, colors, normals, _, confidence = read_dense_ply(folder / "dense.ply")
    if normals is not None:
        length = np.linalg.norm(normals, axis=1)
        if np.all(np.isfinite(length)) and np.all(np.abs(length - 1.0) < 1e-3):
            return points, normals, colors, confidence, "dense.ply"
    from stereoseed.dense.normals import estimate_normals
    from stereoseed.output.reader import load_result

    result = load_result(folder)
    registered = result.registered
    if not registered:
        raise StereoseedError(f"{folder / 'cameras.json'}: no registered camera to turn the normals towards")
    views = camera_viewpoints(points, [result.P[i] for i in registered], [result.sizes[i] for i in registered])
    good = np.all(np.isfinite(points), axis=1)
    normals = np.full(points.shape, np.nan)
    if good.sum() >= 3:
        normals[good] = estimate_normals(points[good], views[good], cfg.normal_neighbours)
    return points, normals, colors, confidence, "estimated"


def mesh_result(result_dir: str | os.PathLike, out: str | os.PathLike | None = None, cfg: Any = None,
                *, lock: bool = True) -> tuple[Path, dict[str, Any]]:
    """Mesh a result folder's ``dense.ply`` (:func:`poisson_mesh`) and write it (:func:`write_mesh`)
    to ``out`` (default ``RESULT/mesh.ply``). Returns the path and the summary.

    cfg: a :class:`MeshConfig`, or a configuration holding one as ``.mesh``; None: the defaults.
    Written into the result folder, the mesh is added to the folder's manifest, so the folder
    stays stereoseed's (a later ``reconstruct --out`` there replaces it with the rest); meanwhile
    the folder's lock is held (``lock=False``: the caller holds it, e.g. a run meshing its own
    folder). Raises :class:`StereoseedError`: no such folder, no dense.ply, the extra missing,
    ``out`` taken by a file stereoseed did not write."""
    cfg = getattr(cfg, "mesh", cfg) or MeshConfig()
    if not isinstance(cfg, MeshConfig):
        raise TypeError(f"cfg must be a MeshConfig or hold one as .mesh, got {type(cfg).__name__}")
    folder = Path(result_dir)
    if not folder.is_dir():
        raise StereoseedError(f"{folder}: no such result folder; give a folder written by stereoseed reconstruct --dense")
    if not (folder / "dense.ply").is_file():
        raise StereoseedError(f"{folder}: no dense.ply to mesh; run stereoseed reconstruct --dense --out {folder} first")
    _pymeshlab()  # before any work: the one-line hint, not a half-done run
    target = Path(out) if out is not None else folder / MESH_NAME
    if same_file(target, folder / "dense.ply"):  # a hard link too
        raise StereoseedError(f"{target}: is the cloud being meshed; give another --out")
    if target.is_dir():
        raise StereoseedError(f"{target}: is a folder; give a file name for the mesh (e.g. {target / MESH_NAME})")
    _refuse_foreign(target)  # before the meshing, not after it
    t0 = time.perf_counter()
    points, normals, colors, confidence, source = _read_cloud(folder, cfg)
    mesh, summary = poisson_mesh(points, normals, colors, cfg, confidence)
    summary = {"normals": source, **summary}
    summary["seconds"] = time.perf_counter() - t0
    inside = _inside(target, folder)
    if inside is None:
        write_mesh(target, mesh)
    else:
        summary["report_html"] = _write_into_result(folder, target, inside, mesh, lock, (points, colors), summary)
    return target, summary


def _inside(target: Path, folder: Path) -> str | None:
    """``target``'s path relative to the result folder, or None when it lies elsewhere."""
    try:
        return str(target.resolve().relative_to(folder.resolve()))
    except ValueError:
        return None


def _write_into_result(folder: Path, target: Path, relative: str, mesh: Mesh, lock: bool,
                       cloud: tuple[np.ndarray, np.ndarray], summary: dict[str, Any]) -> bool:
    """Write the mesh into the result folder and list it in the folder's manifest (when the
    folder has one: a staging folder gets its manifest when it is committed); the folder's
    report.html written again with the mesh shown, its report.json given the mesh's summary
    (:func:`stereoseed.output.report.saved.rewrite_report_html`). Returns whether report.html was
    written."""
    from contextlib import nullcontext

    from stereoseed.output.report.saved import SavedCloud, rewrite_report_html
    from stereoseed.output.result_set import ResultSet, add_to_manifest

    with ResultSet(folder) if lock else nullcontext():
        write_mesh(target, mesh)
        if not add_to_manifest(folder, relative):
            log.warning("%s: its manifest is unreadable; the mesh is not listed in it", folder)
        return rewrite_report_html(folder, mesh, SavedCloud(*cloud), {"mesh": summary}) is not None
