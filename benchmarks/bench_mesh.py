"""The mesh of the dense textured box (issue 37): `stereoseed demo`'s result folder meshed as
`stereoseed mesh` does it, measured against the synthetic scene's true surface.

Figures (distances in cm; the model is in metres):
* faces, vertices, the Poisson faces trimmed, seconds of the meshing;
* median distance of the mesh vertices to the true surface (the box and the ground plane,
  :func:`stereoseed.experiments.evaluation.surface_distance`, as the dense bench measures the
  cloud);
* precision at 0.5 cm: the share of the mesh's vertices, and of its area, within 0.5 cm of the
  true surface;
* completeness at 0.5 cm: the share of true-surface samples within 0.5 cm of the mesh, among the
  samples the dense stage could see (both cameras of one of its image pairs frame them,
  unoccluded): on the object (the box's five faces), on the ground, and over both; the cloud's
  own completeness beside it (samples within 0.5 cm of a cloud point), so the mesh's is read
  against what its input held;
* the share of the area whose face normal points to the outside of the true surface.

Meshed at the default depth 8 (``depth_8``) and at the depth from the cloud's point spacing
(``auto``, ``--depth auto``).

``sphere`` (issue 50): a curved object, :mod:`stereoseed.synthetic.curved` (a textured sphere of
30 cm on a textured ground, 8 views of 640 x 480 on a ring), the sparse run's cameras replaced
by the true ones (the dense stage and the mesh judged alone); the cloud and its mesh (depth 8
and auto): median distance to the true surface of the points / vertices on the sphere, and the
completeness on the sphere at 0.5 % of its size (its diameter): of the sphere's surface a pair
sees, and of the part of it the cloud covers (the mesh judged against what its input held).
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

THRESHOLD_M = 0.005  # the 0.5 cm


def _before():
    from stereoseed.dense.mesh import MeshConfig

    return MeshConfig(depth=8)  # the default depth


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The point (N, 3) of triangle (a[i], b[i], c[i]) nearest to p[i] (all (N, 3)): Ericson's
    Voronoi regions (vertex, edge or face). Degenerate triangles give one of their vertices or
    edges."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        v, w = vb / total, vc / total
        out = a + ab * v[:, None] + ac * w[:, None]
        for edge, start, direction, t in (
                ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a, ab, d1 / (d1 - d3)),
                ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a, ac, d2 / (d2 - d6)),
                ((va <= 0) & (d4 >= d3) & (d5 >= d6), b, c - b, (d4 - d3) / ((d4 - d3) + (d5 - d6)))):
            out = np.where(edge[:, None], start + direction * t[:, None], out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    return np.where(np.isfinite(out), out, a)


def mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, candidates: int = 16) -> np.ndarray:
    """Distance (N,) of each point (N, 3) to the mesh: exact to the ``candidates`` triangles
    whose centroids are nearest, so never below the true distance (a completeness measured with
    it is never flattered)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(faces) == 0:
        return np.full(len(points), np.inf)
    k = min(candidates, len(faces))
    _, idx = cKDTree(vertices[faces].mean(axis=1)).query(points, k=k)
    idx = idx.reshape(len(points), k)
    best = np.full(len(points), np.inf)
    for j in range(k):
        f = faces[idx[:, j]]
        q = closest_points_on_triangles(points, vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]])
        best = np.minimum(best, np.linalg.norm(points - q, axis=1))
    return best


def seen_surface(scene, views: list[int], n: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """True-surface samples (uniform by area on the box and the textured ground disk) that both
    cameras of one consecutive pair of ``views`` see: what the dense stage could have matched.
    Returns points (M, 3) and labels (M,) (0 ground, 1..5 box faces)."""
    points, labels = scene.sample_surface_points(n, np.random.default_rng(seed))
    seen = np.zeros(len(points), bool)
    for a, b in zip(views[:-1], views[1:]):
        todo = ~seen
        seen[todo] = scene.is_visible(a, points[todo]) & scene.is_visible(b, points[todo])
    return points[seen], labels[seen]


def mesh_figures(vertices: np.ndarray, faces: np.ndarray, scene, views: list[int],
                 cloud: np.ndarray | None = None) -> dict:
    """The figures of the module docstring for a mesh of ``scene`` (in its world frame) whose
    dense stage paired ``views`` in order; ``cloud``: the cloud it was made from."""
    from scipy.spatial import cKDTree

    from stereoseed.experiments.evaluation import surface_distance, surface_normal

    d_vertex = surface_distance(vertices)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    centroid = (a + b + c) / 3
    d_face = surface_distance(centroid)
    outward = np.einsum("ij,ij->i", cross, surface_normal(centroid)) > 0
    samples, labels = seen_surface(scene, views)
    d_sample = mesh_distance(samples, vertices, faces)
    box, ground = labels > 0, labels == 0

    def share(x: np.ndarray) -> float | None:
        return float(np.mean(x)) if len(x) else None

    out = {"faces": int(len(faces)), "vertices": int(len(vertices)), "area_m2": float(area.sum()),
           "median_vertex_distance_cm": float(np.median(d_vertex) * 100),
           "p90_vertex_distance_cm": float(np.percentile(d_vertex, 90) * 100),
           "precision_vertices_0.5cm": share(d_vertex <= THRESHOLD_M),
           "precision_area_0.5cm": float(area[d_face <= THRESHOLD_M].sum() / area.sum()),
           "completeness_object_0.5cm": share(d_sample[box] <= THRESHOLD_M),
           "completeness_ground_0.5cm": share(d_sample[ground] <= THRESHOLD_M),
           "completeness_all_0.5cm": share(d_sample <= THRESHOLD_M),
           "outward_area": float(area[outward].sum() / area.sum()),
           "surface_samples_seen": {"object": int(box.sum()), "ground": int(ground.sum())}}
    if cloud is not None:
        d_cloud, _ = cKDTree(cloud).query(samples)
        out["cloud_completeness_object_0.5cm"] = share(d_cloud[box] <= THRESHOLD_M)
        out["cloud_completeness_ground_0.5cm"] = share(d_cloud[ground] <= THRESHOLD_M)
        out["cloud_median_distance_cm"] = float(np.median(surface_distance(cloud)) * 100)
    return out


def _registered(folder: Path) -> list[int]:
    images = json.loads((folder / "cameras.json").read_text())["images"]
    return [i for i, im in enumerate(images) if im["registered"] and im.get("reliable", True)]


def run() -> dict:
    from plyfile import PlyData

    from stereoseed.dense.mesh import MeshConfig, mesh_result
    from stereoseed.experiments.demo import run_demo
    from stereoseed.io.ply import read_ply
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "demo"
        t = time.perf_counter()
        run_demo(folder, n_images=14)  # `stereoseed demo`: the textured box, the pair calibrated from its pattern
        out["demo_seconds"] = time.perf_counter() - t
        scene = render_scene(SceneConfig(n_images=14))
        views = _registered(folder)
        cloud, _ = read_ply(folder / "dense.ply")
        for depth, config in ((8, _before()), (0, MeshConfig(depth=0))):
            path, summary = mesh_result(folder, Path(tmp) / f"mesh_{depth}.ply", config)
            ply = PlyData.read(str(path))
            faces = np.vstack(ply["face"].data["vertex_indices"]).astype(np.int64)
            vertices = np.stack([ply["vertex"].data[k] for k in "xyz"], axis=1).astype(np.float64)
            figures = mesh_figures(vertices, faces, scene, views, cloud if depth == 8 else None)
            out[f"depth_{depth}" if depth else "auto"] = {**figures, "depth": summary["depth"],
                                     "spacing_cm": summary["spacing"] * 100, "poisson_faces": summary["poisson_faces"],
                                     "dropped_far_from_cloud": summary["dropped_far_from_cloud"],
                                     "dropped_low_density": summary["dropped_low_density"],
                                     "cell_cm": summary["cell"] * 100, "points": summary["points"],
                                     "mesh_seconds": summary["seconds"]}
    out["sphere"] = run_sphere()
    return out


def run_sphere(n_images: int = 8) -> dict:
    """The ``sphere`` figures of the module docstring."""
    from scipy.spatial import cKDTree

    from stereoseed.config import Config
    from stereoseed.dense.densify import densify
    from stereoseed.dense.mesh import MeshConfig, poisson_mesh
    from stereoseed.pipeline import reconstruct
    from stereoseed.synthetic.curved import CurvedConfig, render_curved

    t = time.perf_counter()
    scene = render_curved(CurvedConfig(n_images=n_images))
    cfg = Config()
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], cfg)
    for v in recon.registered_views:
        recon.views[v].P = scene.P[v]
    cloud, _ = densify(recon, cfg)
    out: dict = {"registered": len(recon.registered_views), "points": len(cloud.points),
                 "cloud_seconds": time.perf_counter() - t}
    threshold = 0.005 * scene.size
    samples = scene.seen_sphere(recon.registered_views)
    tree = cKDTree(cloud.points)
    covered = tree.query(samples)[0] <= threshold

    def on_sphere(points: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - scene.centre, axis=1) < 1.2 * scene.config.radius

    cloud_median = float(np.median(scene.surface_distance(cloud.points[on_sphere(cloud.points)])))
    out["threshold_cm"] = threshold * 100
    out["cloud"] = {"median_distance_cm": cloud_median * 100, "completeness_seen": float(covered.mean()),
                    "sphere_samples_seen": int(len(samples))}
    for label, config in (("depth_8", _before()), ("auto", MeshConfig(depth=0))):
        mesh, summary = poisson_mesh(cloud.points, cloud.normals, cloud.colors, config, cloud.confidence)
        median = float(np.median(scene.surface_distance(mesh.vertices[on_sphere(mesh.vertices)])))
        reached = mesh_distance(samples, mesh.vertices, mesh.faces) <= threshold
        out[label] = {"depth": summary["depth"], "cell_cm": summary["cell"] * 100,
                      "spacing_cm": summary["spacing"] * 100, "faces": summary["faces"],
                      "median_distance_cm": median * 100, "median_over_cloud": median / cloud_median,
                      "completeness_seen": float(reached.mean()),
                      "completeness_where_the_cloud_is": float(reached[covered].mean()),
                      "completeness_seen_at_1pct": float((mesh_distance(samples, mesh.vertices, mesh.faces)
                                                          <= 2 * threshold).mean()),
                      "mesh_seconds": summary["seconds"]}
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
