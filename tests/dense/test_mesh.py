"""The mesh (issue 37): screened Poisson on the dense cloud (PyMeshLab, the extra ``mesh``),
trimmed to the cloud, coloured from it; `stereoseed mesh` on a result folder."""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from stereoseed.dense.mesh import MeshConfig, camera_viewpoints, mesh_result, poisson_mesh
from stereoseed.errors import StereoseedError
from stereoseed.io.ply import write_ply
from stereoseed.output.result_set import MANIFEST, ResultSet

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_mesh import mesh_distance, mesh_figures  # noqa: E402

def _have_pymeshlab() -> bool:
    try:
        import pymeshlab  # noqa: F401
    except ImportError:
        return False
    return True


needs_pymeshlab = pytest.mark.skipif(not _have_pymeshlab(), reason="PyMeshLab (the mesh extra, in the test extra) "
                                                                   "is not installed")


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    v = ply["vertex"].data
    faces = np.vstack(ply["face"].data["vertex_indices"]).astype(np.int64)
    return (np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64), faces,
            np.stack([v["red"], v["green"], v["blue"]], axis=1))


def _dome(n: int = 30000, radius: float = 0.1, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the upper half of a sphere (an open surface), outward normals, and colours that
    are a function of the direction (red: height, green: x)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > 0]
    return radius * d, d, _dome_colours(d)


def _dome_colours(direction: np.ndarray) -> np.ndarray:
    return np.c_[np.rint(255 * direction[:, 2]), np.rint(127.5 * (direction[:, 0] + 1)),
                 np.full(len(direction), 40)].clip(0, 255).astype(np.uint8)


def _result_folder(folder: Path, points: np.ndarray, normals: np.ndarray | None, colors: np.ndarray,
                   extra: dict[str, Path] | None = None) -> Path:
    """A result folder as stereoseed commits one (its manifest lists its files) holding
    dense.ply and the ``extra`` files copied in."""
    with ResultSet(folder) as results:
        results.check()
        staging = results.open()
        props = None if normals is None else {"nx": normals[:, 0].astype(np.float32),
                                              "ny": normals[:, 1].astype(np.float32),
                                              "nz": normals[:, 2].astype(np.float32)}
        write_ply(staging / "dense.ply", points, colors, props)
        for name, source in (extra or {}).items():
            shutil.copyfile(source, staging / name)
        results.commit()
    return folder


def _mesh_command(argv: list[str]) -> int:
    from stereoseed.cli import mesh

    parser = argparse.ArgumentParser(prog="stereoseed")
    mesh.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["mesh", *argv])
    return args.func(args)


# ---------------------------------------------------------------------- the box, end to end
@pytest.fixture(scope="module")
def dense_box(box_scene, tmp_path_factory):
    """Five images of the textured box reconstructed, the dense stage run, and the result folder
    written as reconstruct writes it (cameras.json, tracks.npz, dense.ply, report.html, the
    manifest)."""
    from stereoseed.config import Config
    from stereoseed.dense.densify import densify
    from stereoseed.experiments.evaluation import TrueCorrespondences
    from stereoseed.pipeline import reconstruct, save_outputs

    scene = box_scene.prefix(5)
    cfg = Config()
    recon, report = reconstruct(scene.images, scene.names, scene.P[:2], cfg, source=TrueCorrespondences(scene))
    folder = tmp_path_factory.mktemp("mesh") / "result"
    with ResultSet(folder) as results:
        results.check()
        staging = results.open()
        cloud, report["dense"] = densify(recon, cfg, staging)
        save_outputs(recon, report, staging, cfg, dense=cloud)
        results.commit()
    return scene, recon, cloud, folder


@needs_pymeshlab
@pytest.mark.slow
def test_mesh_of_the_dense_box_meets_the_issue_figures(dense_box):
    from scipy.spatial import cKDTree

    scene, recon, cloud, folder = dense_box
    page_before = (folder / "report.html").read_text()
    path, summary = mesh_result(folder)
    assert path == folder / "mesh.ply" and summary["normals"] == "dense.ply"
    _assert_the_page_shows_the_mesh(folder, page_before, summary, len(recon.registered_views))
    assert "mesh.ply" in json.loads((folder / MANIFEST).read_text())["files"]
    ResultSet(folder).check()  # still a folder of stereoseed's: a later reconstruct --out may replace it
    vertices, faces, colors = _read_mesh(path)
    assert (len(vertices), len(faces)) == (summary["vertices"], summary["faces"])
    figures = mesh_figures(vertices, faces, scene, recon.registered_views)
    # the issue's figures: >= 10,000 faces, median distance <= 0.05 cm, completeness and precision at 0.5 cm
    assert figures["faces"] >= 10_000
    assert figures["median_vertex_distance_cm"] <= 0.05, figures
    assert figures["completeness_object_0.5cm"] >= 0.95, figures
    assert figures["precision_vertices_0.5cm"] >= 0.90 and figures["precision_area_0.5cm"] >= 0.90, figures
    assert figures["outward_area"] >= 0.99  # faces wound towards the cameras' side
    # trimmed: Poisson's surface beyond the cloud is gone, none of the kept vertices is far from it
    assert summary["dropped_far_from_cloud"] > 0 and summary["poisson_faces"] > summary["faces"]
    gap, _ = cKDTree(cloud.points).query(vertices)
    assert gap.max() <= MeshConfig().max_gap_cells * summary["cell"] * (1 + 1e-5)
    # the colours are the surface's: each vertex seen in image 0 against the pixel it projects to
    seen = scene.is_visible(0, vertices, margin=2)
    uv = np.rint(scene.project(0, vertices[seen])).astype(int)
    pixel = scene.images[0][uv[:, 1], uv[:, 0]][:, ::-1].astype(np.float64)
    assert seen.sum() > 5000
    assert np.median(np.abs(pixel - colors[seen])) <= 8  # measured 4 grey levels
    assert np.corrcoef(pixel.mean(axis=1), colors[seen].astype(np.float64).mean(axis=1))[0, 1] >= 0.9


def _figures_of(page: str) -> dict:
    text = page.split('<script type="application/json" id="figures">', 1)[1].split("</script>", 1)[0]
    return json.loads(text)


def _assert_the_page_shows_the_mesh(folder: Path, before: str, summary: dict, registered: int) -> None:
    """`stereoseed mesh` wrote report.html again from the folder: the mesh in the 3D view, beside
    what the run's page showed (the dense cloud, the sparse cloud, a frustum per registered
    camera), and the mesh's summary in report.json."""
    assert summary["report_html"] is True
    old, new = (_figures_of(page)["view3d"]["data"] for page in (before, (folder / "report.html").read_text()))
    assert not any(t["type"] == "mesh3d" for t in old)
    meshes = [t for t in new if t["type"] == "mesh3d"]
    assert len(meshes) == 1 and len(meshes[0]["i"]) == min(summary["faces"], 100_000)
    assert [t["name"] for t in old] == [t["name"] for t in new if t["type"] != "mesh3d"]  # the rest as the run drew it
    assert any("dense" in t["name"] for t in old) and any("calibrated pair" in t.get("name", "") for t in old)
    report = json.loads((folder / "report.json").read_text())
    assert report["mesh"]["faces"] == summary["faces"] and report["registered"] == registered
    assert "report.html" in json.loads((folder / MANIFEST).read_text())["files"]


@needs_pymeshlab
@pytest.mark.slow
def test_a_cloud_without_normals_is_oriented_towards_the_cameras(dense_box, tmp_path):
    scene, recon, cloud, folder = dense_box
    bare = _result_folder(tmp_path / "bare", cloud.points, None, cloud.colors,
                          {n: folder / n for n in ("cameras.json", "tracks.npz")})
    out = tmp_path / "elsewhere" / "box.ply"
    manifest = (bare / MANIFEST).read_text()
    path, summary = mesh_result(bare, out, MeshConfig(depth=7))
    assert path == out and summary["normals"] == "estimated"
    assert (bare / MANIFEST).read_text() == manifest  # written outside the folder: its manifest is untouched
    vertices, faces, _ = _read_mesh(out)
    figures = mesh_figures(vertices, faces, scene, recon.registered_views)
    assert figures["outward_area"] >= 0.99, figures  # turned the right way round: an inside-out surface fails
    assert figures["median_vertex_distance_cm"] <= 0.1 and figures["precision_area_0.5cm"] >= 0.9, figures


def test_viewpoints_are_the_nearest_cameras_that_frame_each_point():
    from stereoseed.geometry.projection import camera_center

    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])

    def camera(centre, yaw_deg):
        a = np.radians(yaw_deg)
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        return K @ np.c_[R, -R @ np.asarray(centre, float)]

    near = camera([0, 0, -1.0], 0)  # looks along +z
    far = camera([0.2, 0, -3.0], 0)
    away = camera([0, 0, 0.5], 0)  # nearer to the points, but they are behind it
    points = np.array([[0, 0, 0.0], [0.05, 0.02, 0.3], [3.0, 0, 0.0]])  # the last: framed by none
    views = camera_viewpoints(points, [near, -far, away], [(640, 480)] * 3)  # -P: the same camera
    np.testing.assert_allclose(views[:2], [camera_center(near)] * 2, atol=1e-12)
    np.testing.assert_allclose(views[2], camera_center(away), atol=1e-12)  # nearest centre of all
    views = camera_viewpoints(points[:1], [far, away], [(640, 480)] * 2)
    np.testing.assert_allclose(views[0], camera_center(far), atol=1e-12)


# ---------------------------------------------------------------------- the dome: exact answers
@needs_pymeshlab
def test_the_mesh_of_an_open_dome_keeps_to_the_dome():
    points, normals, colors = _dome()
    mesh, summary = poisson_mesh(points, normals, colors, MeshConfig(depth=6))
    cell = summary["cell"]
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert np.median(np.abs(radius - 0.1)) < 0.05 * cell  # on the sphere
    # Poisson closes the dome below its rim; the trimmed mesh stops within max_gap_cells of it
    assert mesh.vertices[:, 2].min() >= -MeshConfig().max_gap_cells * cell
    assert summary["poisson_vertices"] > summary["vertices"]
    # and covers the whole dome: samples of it lie on the mesh
    q = np.random.default_rng(1).normal(size=(4000, 3))
    q = q[q[:, 2] > 0] / np.linalg.norm(q[q[:, 2] > 0], axis=1, keepdims=True)
    assert np.all(mesh_distance(0.1 * q, mesh.vertices, mesh.faces) < 0.25 * cell)
    # faces wound outwards, normals outwards, colours those of the cloud where the vertex is
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    assert np.all(np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) > 0)
    assert np.mean(np.einsum("ij,ij->i", mesh.normals, mesh.vertices / radius[:, None]) > 0.9) > 0.99
    expected = _dome_colours(mesh.vertices / radius[:, None]).astype(float)
    error = np.abs(mesh.colors - expected)
    inner = mesh.vertices[:, 2] > 3 * cell  # the rim's neighbours are all on one side of it
    assert np.median(error) <= 2 and error[inner].max() <= 10
    assert mesh.colors.dtype == np.uint8 and len(mesh.density) == len(mesh.vertices)


@needs_pymeshlab
def test_each_trim_alone_removes_the_surface_poisson_invents_below_the_rim():
    points, normals, colors = _dome()
    lowest = {}
    for name, cfg in {"none": MeshConfig(depth=6, max_gap_cells=1000.0, density_drop=1000.0),
                      "density": MeshConfig(depth=6, max_gap_cells=1000.0),
                      "distance": MeshConfig(depth=6, max_gap_cells=2.0, density_drop=1000.0)}.items():
        mesh, summary = poisson_mesh(points, normals, colors, cfg)
        lowest[name] = mesh.vertices[:, 2].min() / summary["cell"]
        if name == "density":
            assert summary["dropped_low_density"] > 0 and summary["dropped_far_from_cloud"] == 0
    assert lowest["none"] < -10  # untrimmed: a bubble under the dome (measured -17 cells)
    assert lowest["density"] > -5 and lowest["distance"] >= -2


@needs_pymeshlab
def test_too_few_points_are_refused():
    points, normals, colors = _dome(n=120)
    with pytest.raises(StereoseedError, match="fewer than the 100"):
        poisson_mesh(points[:50], normals[:50], colors[:50])


# ---------------------------------------------------------------------- the command
@needs_pymeshlab
def test_the_command_writes_the_mesh_into_the_result_and_replaces_only_its_own(tmp_path, capsys):
    points, normals, colors = _dome()
    folder = _result_folder(tmp_path / "dome", points, normals, colors)
    assert _mesh_command([str(folder), "--depth", "6"]) == 0
    line = capsys.readouterr().out.strip()
    vertices, faces, _ = _read_mesh(folder / "mesh.ply")
    assert line.startswith(f"mesh: {len(faces)} faces, {len(vertices)} vertices from {len(points)} points")
    assert line.endswith(f"wrote {folder / 'mesh.ply'}")
    first = (folder / "mesh.ply").stat().st_ino
    assert _mesh_command([str(folder), "--depth", "5"]) == 0  # its own mesh: replaced (atomically: a new file)
    assert "depth 5 " in capsys.readouterr().out
    assert (folder / "mesh.ply").stat().st_ino != first and len(_read_mesh(folder / "mesh.ply")[1]) < len(faces)
    files = json.loads((folder / MANIFEST).read_text())["files"]
    assert files.count("mesh.ply") == 1 and files == sorted(files)
    assert not list(tmp_path.glob(".dome.lock")) and not list(folder.glob(".mesh.ply.*"))  # no lock, no temporary left


@needs_pymeshlab
def test_the_command_refuses_to_overwrite_what_it_did_not_write(tmp_path):
    points, normals, colors = _dome(n=3000)
    folder = _result_folder(tmp_path / "dome", points, normals, colors)
    mine = tmp_path / "mine.ply"
    mine.write_bytes(b"ply\nmy own scan\n")
    with pytest.raises(StereoseedError, match="mine.ply: exists and is not a mesh stereoseed wrote"):
        _mesh_command([str(folder), "--out", str(mine)])
    assert mine.read_bytes() == b"ply\nmy own scan\n"
    before = (folder / "dense.ply").read_bytes()
    with pytest.raises(StereoseedError, match="is the cloud being meshed"):
        mesh_result(folder, folder / "dense.ply")
    write_ply(folder / "sparse.ply", points[:10])  # stereoseed's, but no mesh
    with pytest.raises(StereoseedError, match="sparse.ply: exists and is not a mesh"):
        mesh_result(folder, folder / "sparse.ply")
    assert (folder / "dense.ply").read_bytes() == before
    with pytest.raises(StereoseedError, match="is a folder"):
        mesh_result(folder, tmp_path)


def test_a_result_without_dense_ply_or_without_the_extra_is_one_line(tmp_path, monkeypatch):
    folder = tmp_path / "sparse_only"
    folder.mkdir()
    with pytest.raises(StereoseedError, match=r"no dense.ply to mesh; run stereoseed reconstruct --dense"):
        _mesh_command([str(folder)])
    with pytest.raises(StereoseedError, match="no such result folder"):
        mesh_result(tmp_path / "missing")
    points, _, colors = _dome(n=3000)
    write_ply(folder / "dense.ply", points, colors)
    monkeypatch.setitem(sys.modules, "pymeshlab", None)  # as if the extra were not installed
    with pytest.raises(StereoseedError) as error:
        _mesh_command([str(folder)])
    assert "pip install 'stereoseed[mesh]'" in str(error.value) and "\n" not in str(error.value)
    assert not (folder / "mesh.ply").exists()


# ---------------------------------------------------------------------- the measures
def test_mesh_distance_is_the_exact_distance_to_a_square():
    """The benchmark's point-to-mesh distance on the unit square z = 0 (two triangles): above
    it the height, beside an edge or a corner the distance to it."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    points = np.array([[0.3, 0.6, 0.2], [0.5, 0.5, -0.1], [1.5, 0.5, 0.2], [0.5, -0.3, 0.4], [-1, -1, 1],
                       [2, 3, 0], [0.2, 0.2, 0]])
    expected = [0.2, 0.1, np.hypot(0.5, 0.2), 0.5, np.sqrt(3), np.hypot(1, 2), 0.0]
    np.testing.assert_allclose(mesh_distance(points, vertices, faces), expected, atol=1e-12)


def test_mesh_config_refuses_what_cannot_work():
    for bad in ({"depth": 3}, {"depth": 13}, {"scale": 0.9}, {"max_gap_cells": 0}, {"density_drop": -1},
                {"color_neighbours": 0}, {"threads": -1}, {"point_weight": -1}, {"min_points": 5}):
        with pytest.raises(ValueError, match="MeshConfig"):
            MeshConfig(**bad)


def test_reconstruct_mesh_writes_the_mesh_with_the_run(tmp_path, small_box_scene, capsys):
    """`reconstruct --dense --mesh`: the run's folder holds mesh.ply, listed as stereoseed's; without
    --dense the run is refused before any work."""
    from scene_helpers import scene_on_disk

    from stereoseed.cli import main

    paths, calib = scene_on_disk(small_box_scene.prefix(4), tmp_path / "walk")
    out = tmp_path / "out"
    assert main(["reconstruct", str(paths["images_txt"]), "--calib", str(calib), "--out", str(out), "--dense",
                 "--mesh", "--quiet"]) == 0
    mesh = _read_mesh(out / "mesh.ply")
    assert len(mesh[1]) > 1000  # faces
    assert "mesh.ply" in (out / MANIFEST).read_text()
    assert json.loads((out / "report.json").read_text())["mesh"]["faces"] == len(mesh[1])
    assert '"type": "mesh3d"' in (out / "report.html").read_text() or '"type":"mesh3d"' in (out / "report.html").read_text()
    assert f"mesh: {len(mesh[1])} faces" in capsys.readouterr().out
    assert main(["reconstruct", str(paths["images_txt"]), "--calib", str(calib), "--out", str(tmp_path / "o2"),
                 "--mesh", "--quiet"]) == 2
    assert "add --dense" in capsys.readouterr().err


# ---------------------------------------------------------------------- curved objects (issue 50)
def _domes(n: int = 2000, radius: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Four small domes 1.5 apart (objects on a table: a wide extent, a fine point spacing):
    points, outward normals, colours, the domes' centres."""
    d = np.random.default_rng(0).normal(size=(2 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > 0]
    centres = np.array([[0, 0, 0], [1.5, 0, 0], [0, 1.5, 0], [1.5, 1.5, 0.0]])
    points = np.vstack([c + radius * d for c in centres])
    return points, np.vstack([d] * 4), np.full((len(points), 3), 128, np.uint8), centres


@needs_pymeshlab
def test_the_poisson_depth_follows_the_point_spacing_and_keeps_curved_surfaces():
    from stereoseed.dense.mesh import point_spacing, poisson_depth

    points, normals, colors, centres = _domes()
    spacing = point_spacing(points)
    mesh, summary = poisson_mesh(points, normals, colors, MeshConfig(depth=0))
    extent = 1.1 * np.ptp(points, axis=0).max()
    # the shallowest depth whose cell is within 4 spacings
    assert summary["depth"] == int(np.ceil(np.log2(extent / (4 * spacing)))) and summary["cell"] <= 4 * spacing
    assert poisson_depth(points[::4], MeshConfig(depth=0), point_spacing(points[::4])) == summary["depth"] - 1
    assert poisson_depth(points, MeshConfig(depth=7), spacing) == 7  # a depth given is kept
    assert poisson_depth(points, MeshConfig(depth=0, max_auto_depth=8), spacing) == 8
    error = np.min([np.abs(np.linalg.norm(mesh.vertices - c, axis=1) - 0.05) for c in centres], axis=0)
    # on the domes within a small part of the spacing (measured 0.025 spacings; the fixed depth 8
    # of before: 0.072, its cell 5.3 spacings)
    assert np.median(error) <= 0.045 * spacing, (np.median(error) / spacing, summary)


@needs_pymeshlab
def test_points_below_the_confidence_are_left_out_of_the_mesh():
    points, normals, colors = _dome()
    rng = np.random.default_rng(3)
    confidence = np.full(len(points), 0.9)
    # a floater sheet in front of the dome: contradicted by the other views (confidence 0.3)
    sheet = np.c_[rng.uniform(-0.05, 0.05, (2000, 2)), np.full(2000, 0.15)]
    cloud = np.vstack([points, sheet])
    up = np.vstack([normals, np.tile([0.0, 0, 1], (2000, 1))])
    both = np.vstack([colors, np.zeros((2000, 3), np.uint8)])
    mesh, summary = poisson_mesh(cloud, up, both, MeshConfig(depth=6), np.r_[confidence, np.full(2000, 0.3)])
    assert summary["points"] == len(points) and summary["weighted_by_confidence"]
    assert mesh.vertices[:, 2].max() <= 0.1 + 0.5 * summary["cell"]  # no surface of the sheet's
    mesh, _ = poisson_mesh(cloud, up, both, MeshConfig(depth=6, min_confidence=0.0), np.r_[confidence, np.full(2000, 0.3)])
    assert mesh.vertices[:, 2].max() > 0.14  # kept when asked: the sheet is meshed


@needs_pymeshlab
def test_the_mesh_of_a_rendered_sphere_keeps_its_clouds_accuracy():
    """A textured sphere on a textured ground rendered in three views (320 x 240), the sparse run
    on them (its cameras replaced by the true ones: the dense stage and the mesh judged alone),
    the dense stage, the mesh: within 1.3 times the cloud's median error on the sphere, and
    covering the sphere wherever its cloud does (within 0.5 % of its size)."""
    from scipy.spatial import cKDTree

    from stereoseed.config import Config
    from stereoseed.dense.densify import densify
    from stereoseed.pipeline import reconstruct
    from stereoseed.synthetic.curved import CurvedConfig, render_curved

    scene = render_curved(CurvedConfig(n_images=3, width=320, height=240, focal_px=800.0))
    cfg = Config()
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], cfg)
    assert recon.registered_views == [0, 1, 2]
    for v in recon.registered_views:
        recon.views[v].P = scene.P[v]
    cloud, _ = densify(recon, cfg)
    mesh, summary = poisson_mesh(cloud.points, cloud.normals, cloud.colors, MeshConfig(depth=0), cloud.confidence)

    def on_sphere(points):
        return np.linalg.norm(points - scene.centre, axis=1) < 1.2 * scene.config.radius

    cloud_error = np.median(scene.surface_distance(cloud.points[on_sphere(cloud.points)]))
    mesh_error = np.median(scene.surface_distance(mesh.vertices[on_sphere(mesh.vertices)]))
    assert cloud_error < 0.002 * scene.size  # the cloud itself is good (measured 0.1 mm)
    assert mesh_error <= 1.3 * cloud_error, (mesh_error, cloud_error, summary)
    threshold = 0.005 * scene.size
    samples = scene.seen_sphere(recon.registered_views, n=20_000)
    covered = cKDTree(cloud.points).query(samples)[0] <= threshold
    assert covered.sum() > 2000
    assert np.mean(mesh_distance(samples[covered], mesh.vertices, mesh.faces) <= threshold) >= 0.95
