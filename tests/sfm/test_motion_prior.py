"""The motion prior: a camera placed from the predicted pixels when no epipolar geometry is found."""

from ring_helpers import ring, centre_errors
from stereoseed.config import Config
from stereoseed.sfm.mapper import initialise, insert_view
from stereoseed.sfm.registration.base import FoundBy


def test_without_epipolar_geometry_the_motion_prior_places_the_camera():
    images, names, Ps, source = ring(6, step_deg=10.0, no_epipolar=(4,))
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    reports = [insert_view(recon, k, cfg, source) for k in range(2, 6)]
    assert reports[2]["matches"] == 0 and reports[2]["registered_by"] == FoundBy.MOTION_PRIOR
    assert reports[2]["motion_prior_search"]["radius_fraction"] == min(cfg.motion_prior.radius_fractions)
    assert centre_errors(recon, Ps).max() < 0.003


def test_the_wide_search_finds_a_camera_the_prediction_misses():
    # image 4 looks 12 cm to the side of the others' target: every point lands ~70 px from its
    # predicted pixel, beyond the near search (8 % of 640 px), within the wide one (16 %)
    images, names, Ps, source = ring(6, step_deg=10.0, no_epipolar=(4,), targets={4: (0.12, -0.05, 0.2)})
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    reports = [insert_view(recon, k, cfg, source) for k in range(2, 6)]
    assert reports[2]["registered_by"] == FoundBy.MOTION_PRIOR, reports[2]
    assert reports[2]["motion_prior_search"]["radius_fraction"] == max(cfg.motion_prior.radius_fractions)
    assert centre_errors(recon, Ps).max() < 0.003
