import cv2
import numpy as np

from stereoseed.estimators.pose import refine_pose
from stereoseed.geometry.projection import camera_center, decompose_projection, project
from geometry_helpers import box_points, ring_camera


def _moved(K, R, t, w, dt):
    return cv2.Rodrigues(np.asarray(w, float))[0] @ R, t + np.asarray(dt, float)


def test_finds_the_pose_from_a_start_off_and_states_its_spread():
    """A camera started 0.06 degrees and 3 mm off comes back to the truth; over 100 draws of
    0.3 px pixel noise the poses spread as the stated covariance says."""
    rng = np.random.default_rng(0)
    P = ring_camera(30.0)[3]
    K, R, t = decompose_projection(P)
    X = box_points(rng, 120)
    clean = project(P, X)
    R0, t0 = _moved(K, R, t, [0.001, -0.0005, 0.0008], [0.002, -0.001, 0.002])
    increments, stated = [], None
    for _ in range(100):
        found = refine_pose(K, R0, t0, X, clean + rng.normal(0.0, 0.3, clean.shape))
        assert found is not None and found.converged and found.n_used == 120
        increments.append(found.increment)
        stated = found.covariance
    R1 = cv2.Rodrigues(np.mean(increments, axis=0)[:3])[0] @ R0
    assert np.degrees(np.arccos(np.clip((np.trace(R1 @ R.T) - 1) / 2, -1, 1))) < 0.01
    t1 = t0 + np.mean(increments, axis=0)[3:]
    assert np.linalg.norm(-R1.T @ t1 - camera_center(P)) < 1e-3
    np.testing.assert_allclose(np.std(increments, axis=0, ddof=1), np.sqrt(np.diag(stated)), rtol=0.25)


def test_pairs_far_off_carry_no_weight_and_too_few_give_none():
    rng = np.random.default_rng(1)
    P = ring_camera(60.0)[3]
    K, R, t = decompose_projection(P)
    X = box_points(rng, 60)
    x = project(P, X)
    x[:10] += 40.0  # ten wrong matches
    found = refine_pose(K, R, t + [0.003, 0.0, 0.0], X, x)
    assert found.n_used == 50 and found.rms_px < 1e-6
    assert refine_pose(K, R, t, X[:5], x[:5]) is None
