import numpy as np
import pytest

from stereoseed.geometry.projection import camera_center, decompose_projection, normalize_projection, project
from stereoseed.config import ResectionConfig
from stereoseed.errors import StereoseedError
from stereoseed.estimators.resection import implausible_intrinsics, resect
from geometry_helpers import box_points, ring_camera


def test_robust_resection_rejects_outliers():
    rng = np.random.default_rng(0)
    P = ring_camera(60.0, f=900.0)[3]
    X = box_points(rng, 300)
    x = project(P, X) + rng.normal(0, 0.3, (300, 2))
    bad = rng.random(300) < 0.4
    x[bad] += rng.uniform(-60, 60, (bad.sum(), 2))
    res = resect(X, x, scores=rng.uniform(0.8, 1.0, 300), image_size=(640, 480))
    assert not np.any(res.inliers & bad & (np.linalg.norm(project(P, X) - x, axis=1) > 2.0))
    assert res.inliers[~bad].mean() > 0.97
    assert np.linalg.norm(camera_center(res.P) - camera_center(P)) < 0.01
    assert res.rms_px < 0.6


@pytest.mark.parametrize("model", ["free", "zero-skew", "focal"])
def test_models_recover_exact_camera(model):
    rng = np.random.default_rng(1)
    ref_K = ring_camera(0.0, f=800.0)[0]
    K, R, t, P = ring_camera(40.0, f=880.0)  # same pp/aspect as ref_K: all models can fit it
    X = box_points(rng, 100)
    res = resect(X, project(P, X), model=model, reference_K=ref_K)
    np.testing.assert_allclose(res.P, normalize_projection(P), atol=1e-6 * np.abs(P).max())


def test_constrained_model_reduces_noise_sensitivity():
    rng = np.random.default_rng(2)
    ref_K = ring_camera(0.0, f=800.0)[0]
    P = ring_camera(40.0, f=880.0)[3]
    C = camera_center(P)
    X = box_points(rng, 60)
    errs = {"free": [], "focal": []}
    for _ in range(10):
        x = project(P, X) + rng.normal(0, 1.0, (60, 2))
        for model in errs:
            errs[model].append(np.linalg.norm(camera_center(resect(X, x, model=model, reference_K=ref_K).P) - C))
    assert np.median(errs["focal"]) < np.median(errs["free"])


def test_too_few_and_degenerate():
    rng = np.random.default_rng(3)
    P = ring_camera(0.0)[3]
    X = box_points(rng, 40)
    with pytest.raises(StereoseedError, match="at least 6"):
        resect(X[:5], project(P, X[:5]))
    flat = X.copy()
    flat[:, 2] = 0.0
    with pytest.raises(StereoseedError, match="coplanar"):
        resect(flat, project(P, flat))
    with pytest.raises(StereoseedError, match="agree"):
        resect(X, rng.uniform(0, 640, (40, 2)), ResectionConfig(min_inliers=12))


@pytest.mark.parametrize("zoom", [1.0, 1.1])
def test_focal_model_keeps_the_previous_zoom_unless_the_data_pay_for_a_new_one(zoom):
    """A focal-only camera against 'the zoom did not move' (BIC): with an unchanged focal length
    the previous intrinsics are kept exactly; a 10 % zoom is found."""
    rng = np.random.default_rng(3)
    prev_K = ring_camera(0.0, f=800.0)[0]
    P = ring_camera(40.0, f=800.0 * zoom)[3]
    X = box_points(rng, 40)
    x = project(P, X) + rng.normal(0, 0.3, (40, 2))
    res = resect(X, x, model="focal", reference_K=prev_K, fallback_K=prev_K)
    K = decompose_projection(res.P)[0]
    if zoom == 1.0:
        assert K[0, 0] == pytest.approx(800.0, rel=1e-9) and res.info["model"] == "fixed"
    else:
        assert K[0, 0] == pytest.approx(880.0, rel=0.01) and res.info["model"] == "focal"
    assert np.linalg.norm(camera_center(res.P) - camera_center(P)) < 0.01


def test_a_new_focal_length_needs_strong_evidence():
    # a 3 % zoom seen by 40 points with 0.3 px noise: the BIC prefers it by less than 6 (positive,
    # not strong evidence), so the previous focal length is kept; without the margin it is taken
    rng = np.random.default_rng(0)
    prev_K = ring_camera(0.0, f=800.0)[0]
    P = ring_camera(40.0, f=824.0)[3]
    X = box_points(rng, 40)
    x = project(P, X) + rng.normal(0, 0.3, (40, 2))
    strict = resect(X, x, model="focal", reference_K=prev_K, fallback_K=prev_K)
    lenient = resect(X, x, ResectionConfig(zoom_evidence_bic=0.0), model="focal", reference_K=prev_K, fallback_K=prev_K)
    assert ResectionConfig().zoom_evidence_bic == 6.0
    assert strict.info["model"] == "fixed" and decompose_projection(strict.P)[0][0, 0] == pytest.approx(800.0)
    assert lenient.info["model"] == "focal" and decompose_projection(lenient.P)[0][0, 0] == pytest.approx(824.0, rel=0.01)


def test_implausible_intrinsics_names_what_no_physical_camera_does():
    ref_K = ring_camera(0.0, f=800.0)[0]
    size = (640, 480)
    assert implausible_intrinsics(ring_camera(40.0, f=880.0)[3], ref_K, size) is None  # a zoom is fine
    assert "principal point" in implausible_intrinsics(ring_camera(40.0, pp=(320.0, 40.0))[3], ref_K, size)
    assert "aspect" in implausible_intrinsics(ring_camera(40.0, aspect=1.1)[3], ref_K, size)
    assert "skew" in implausible_intrinsics(ring_camera(40.0, skew=40.0)[3], ref_K, size)
    # a free resection from well-spread points with detector noise stays within the bounds
    rng = np.random.default_rng(4)
    P = ring_camera(40.0, f=880.0)[3]
    X = box_points(rng, 80)
    res = resect(X, project(P, X) + rng.normal(0, 0.3, (80, 2)), image_size=size)
    assert implausible_intrinsics(res.P, ref_K, size) is None


def _samples_drawn_in_python(rng, n_samples, p, cells, distinct_cells):
    """The sampling rule written plainly: the first fitting of 12 weighted draws per sample,
    then, sample after sample, uniform draws (one rng.integers call each) for a short one."""
    draws = rng.choice(len(p), size=(n_samples, 12), p=p)
    samples = []
    for row in draws:
        chosen = []
        for idx in row:
            if idx not in chosen and not (distinct_cells and cells[idx] in cells[chosen]):
                chosen.append(int(idx))
            if len(chosen) == 6:
                break
        samples.append(chosen)
    for chosen in samples:
        while len(chosen) < 6:
            idx = int(rng.integers(len(p)))
            if idx not in chosen:
                chosen.append(idx)
    return np.array(samples)


@pytest.mark.parametrize("n_cells", [3, 6, 40])
def test_compiled_sampling_draws_the_plain_rule_s_samples_and_leaves_the_generator_alike(n_cells):
    """Few image cells make most samples short of 6 distinct cells: their completion draws from
    the generator inside the kernel, and must give the same samples and the same generator
    state as the plain rule (the RANSAC's results then do not depend on how it is compiled)."""
    from stereoseed.estimators.resection import _draw_samples

    n = 50
    gen = np.random.default_rng(7)
    p = gen.random(n)
    p /= p.sum()
    cells = gen.integers(0, n_cells, n)
    for distinct in (True, False):
        ours, plain = np.random.default_rng(3), np.random.default_rng(3)
        got = _draw_samples(ours, 400, p, cells, distinct)
        want = _samples_drawn_in_python(plain, 400, p, cells, distinct)
        assert np.array_equal(got, want)
        assert ours.bit_generator.state == plain.bit_generator.state
        assert all(len(set(s)) == 6 for s in got.tolist())
