"""The modes: the paper's two-view points and unlinked observations; the accurate mode's held intrinsics."""
import numpy as np

from ring_helpers import ring
from stereoseed.config import Config, PipelineConfig
from stereoseed.sfm.mapper import initialise, insert_view


def test_the_paper_mode_keeps_two_view_points_and_unlinked_chained_observations():
    images, names, Ps, source = ring(5)
    cfg = Config(pipeline=PipelineConfig(mode="paper"))
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    insert_view(recon, 2, cfg, source)
    unlinked = ~recon.obs_linked
    # the chained old points are observed in view 2 for the cost only; their interest points
    # stand for the new two-view points, through which the next insertion chains
    assert unlinked.any() and set(recon.obs_view[unlinked]) <= {1, 2}
    v2 = recon.views[2]
    stands_for = v2.point_of_feature[recon.obs_feature[unlinked & (recon.obs_view == 2)]]
    assert np.all(stands_for != recon.obs_point[unlinked & (recon.obs_view == 2)])
    live = recon.alive & (recon.track_lengths() > 0)
    assert np.all(recon.track_lengths()[live] >= 2)


def test_local_ba_holds_the_calibrated_intrinsics_until_a_zoom_is_found():
    """accurate mode, "focal" model: the BA after an insertion runs on the "fixed" model while no
    image after the pair was found zoomed; then, and in paper mode, on the run's model."""
    from stereoseed.sfm.strategy import mode_of
    from stereoseed.scene.reconstruction import Reconstruction, View

    def _unzoomed_held(recon, options):  # the BA options the mode gives after an insertion
        return mode_of(options.pipeline).adjustment_options(recon, options)

    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    recon = Reconstruction([View(name=f"v{i}", P=P) for i in range(4)])
    cfg = Config().mapper_options()
    assert _unzoomed_held(recon, cfg).pipeline.camera_model == "fixed"
    recon.views[3].zoomed = True
    assert _unzoomed_held(recon, cfg) is cfg
    recon.views[3].zoomed = False
    paper = Config(pipeline=PipelineConfig(mode="paper")).mapper_options()
    assert _unzoomed_held(recon, paper) is paper
    no_hold = Config(pipeline=PipelineConfig(hold_unzoomed=False)).mapper_options()
    assert _unzoomed_held(recon, no_hold) is no_hold


def test_each_mode_owns_the_defaults_the_resolved_config_takes():
    from stereoseed.sfm.modes import AccurateMode, PaperMode
    from stereoseed.sfm.strategy import mode_of

    for mode, cls in (("paper", PaperMode), ("accurate", AccurateMode)):
        cfg = Config(pipeline=PipelineConfig(mode=mode)).resolve()
        strategy = mode_of(cfg.pipeline)
        assert isinstance(strategy, cls) and strategy.name == mode
        d = strategy.defaults
        assert (cfg.pipeline.camera_model, cfg.pipeline.window, cfg.pipeline.ba) == (d.camera_model, d.window, d.ba)
        assert cfg.outliers.factor == d.outlier_factor and cfg.motion_prior.explain_px == d.explain_px
    # what the user sets wins over the mode's default
    mine = Config(pipeline=PipelineConfig(mode="paper", camera_model="zero-skew")).resolve()
    assert mine.pipeline.camera_model == "zero-skew"


def test_a_window_holding_a_weakly_placed_camera_does_not_decide_the_walk_s_lens(box_scene, monkeypatch):
    # the box's camera zooms by up to 10 % at every image: the first resection that finds it
    # decides the walk's lens, unless a camera of its window rests on weak evidence (a zoom
    # explains that camera's offset as well as the offset itself does)
    import stereoseed.sfm.mapper as mapper
    from stereoseed.pipeline import reconstruct

    n = 6
    images, names, P_pair = box_scene.images[:n], box_scene.names[:n], box_scene.P[:2]
    _, report = reconstruct(images, names, P_pair, Config())
    first = next(k for k, r in enumerate(report["per_image"]) if r.get("zoom_evidence", {}).get("kept"))
    before = first - 1
    monkeypatch.setattr(mapper, "_weakly_placed", lambda recon, v: v == before)
    _, held = reconstruct(images, names, P_pair, Config())
    evidence = held["per_image"][first]["zoom_evidence"]
    assert not evidence["kept"] and evidence["weakly_placed_in_window"] == [names[before]]


def test_a_camera_is_weakly_placed_when_a_weak_sparse_registration_was_kept():
    from stereoseed.sfm.mapper import _weakly_placed

    images, names, Ps, source = ring(5)
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    insert_view(recon, 2, cfg, source)
    assert recon.views[2].found_by == "epipolar chain" and not _weakly_placed(recon, 2)
    report = recon.reports()[2]
    recon.record(2, {**report, "sparse_weak": "13 sparse resection inliers < 24"})
    assert _weakly_placed(recon, 2)
    recon.record(2, {**report, "registered_by": "motion prior"})
    assert not _weakly_placed(recon, 2)  # a trusted prediction (enough inliers, no gap)
    recon.record(2, {**report, "registered_by": "motion prior", "sparse_weak": "the motion prior's camera, predicted "
                                                                              "across 1 view"})
    assert _weakly_placed(recon, 2)
    recon.record(2, {**report, "registered_by": "quasi-dense", "sparse_weak": "13 sparse resection inliers < 24"})
    assert not _weakly_placed(recon, 2)  # the propagated matches placed it
