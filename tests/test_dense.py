"""Quasi-dense stage: triangulation + fusion against the synthetic surface (issue 5)."""
import numpy as np
import pytest

from stereoseed.config import Config
from stereoseed.dense import densify, fuse, supported
from stereoseed.evaluation import TrueCorrespondences, surface_distance
from stereoseed.io import read_ply
from stereoseed.pipeline import reconstruct
from stereoseed.synthetic import SceneConfig, render_scene


@pytest.fixture(scope="module")
def short_ring():
    return render_scene(SceneConfig(n_images=4))


def test_fuse_merges_duplicates_and_keeps_colour():
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 1, (1000, 3))
    pts = np.vstack([base, base + 1e-5])
    cols = np.vstack([np.full((1000, 3), 100, np.uint8), np.full((1000, 3), 200, np.uint8)])
    fused, fcol = fuse(pts, cols, voxel=1e-3)
    assert 1000 <= len(fused) < 1100  # the two copies fall in one voxel (bar a few on voxel borders)
    assert np.all(fcol[:10] == 150) or np.any(fcol == 150)


def test_dense_cloud_lies_on_the_true_surface(short_ring, tmp_path):
    cfg = Config()
    recon, _ = reconstruct(short_ring.images, short_ring.names, short_ring.P[:2], cfg,
                           source=TrueCorrespondences(short_ring))
    report = densify(recon, cfg, tmp_path)
    pts, cols = read_ply(tmp_path / "dense.ply")
    assert len(pts) == report["points"] > 200_000
    assert report["points_before_fusion"] >= report["points"]
    for pair in report["pairs"]:
        assert pair["matches"] >= pair["in_front"] >= pair["small_reprojection"] >= pair["wide_angle"] > 50_000
    d = surface_distance(pts)
    assert np.median(d) < 0.002
    assert np.mean(d < 0.01) > 0.95


def test_support_keeps_surfaces_and_drops_isolated_points():
    rng = np.random.default_rng(1)
    surface = np.c_[rng.uniform(0, 0.1, (3000, 2)), np.zeros(3000)]
    pts = np.vstack([surface, surface + rng.normal(0, 1e-4, surface.shape), rng.uniform(0, 0.1, (300, 3))])
    sources = np.r_[np.zeros(3000), np.ones(3000), np.full(300, 2)].astype(int)
    keep = supported(pts, sources, size=2e-3, min_sources=2)
    assert keep[:6000].mean() > 0.97  # the surface seen by two pairs stays
    assert keep[6000:].mean() < 0.05  # points only one pair claims go


def test_temple_dense_cloud_stays_inside_the_object_box(temple_run, tmp_path):
    recon, _, _ = temple_run
    report = densify(recon, Config(), tmp_path)
    pts, _ = read_ply(tmp_path / "dense.ply")
    assert len(pts) == report["points"] > 200_000
    # the dataset README's tight bounding box, grown by 1 cm
    lo = np.array([-0.073568, 0.021728, -0.012445]) - 0.01
    hi = np.array([0.028855, 0.181892, 0.062736]) + 0.01
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    assert inside.mean() >= 0.98, inside.mean()
