"""The mapper's operations on a small synthetic problem (exact correspondences, no images), the
way COLMAP tests its incremental mapper: initialise, insert, finish; a failed insertion leaves no trace."""
import numpy as np
import pytest

from ring_helpers import as_if_placed_by, ring, state, assert_same_state, walked
from stereoseed.config import Config, PipelineConfig
from stereoseed.sfm.mapper import finish, initialise, insert_view
from stereoseed.scene.camera_life import Flag


def test_initialise_triangulates_the_shared_points_of_the_pair():
    images, names, Ps, source = ring(3)
    recon, report = initialise(images, names, Ps[:2], Config(), source)
    shared = len(np.intersect1d(source.ids[0], source.ids[1]))
    assert report["new_points"] == len(recon.points) and len(recon.points) >= 0.95 * shared
    X_true = source.points[source.ids[0][recon.obs_feature[recon.obs_view == 0]]]
    assert np.abs(recon.points - X_true).max() < 0.002  # 0.1 px noise at 1.4 m
    assert np.all(recon.views[0].point_of_feature[recon.obs_feature[recon.obs_view == 0]] >= 0)


def test_the_step_by_step_api_survives_a_failing_image():
    images, names, Ps, source = ring(7, blind=(4,))
    cfg = Config(pipeline=PipelineConfig(mode="paper"))
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    statuses = [insert_view(recon, k, cfg, source)["status"] for k in range(2, 7)]
    assert statuses == ["registered", "registered", "failed", "registered", "registered"]
    finish(recon, cfg, source)
    assert recon.registered_views == [0, 1, 2, 3, 5, 6]


def _raising(error):
    def raise_it(*args, **kwargs):
        raise error
    return raise_it


@pytest.mark.parametrize("module, function", [("sfm.registration.base", "implausible_motion"), ("sfm.modes", "adjust")])
def test_a_numerical_failure_fails_the_image_and_changes_nothing(started, monkeypatch, module, function):
    # during the registration (nothing committed yet) or after the commit (rolled back)
    import importlib

    recon, Ps, cfg, source = started
    before = state(recon)
    monkeypatch.setattr(importlib.import_module(f"stereoseed.{module}"), function,
                        _raising(np.linalg.LinAlgError("Singular matrix")))
    report = insert_view(recon, 4, cfg, source)
    assert report["status"] == "failed" and "numerical failure" in report["reason"]
    assert_same_state(before, state(recon))
    assert not recon.views[4].registered


def test_an_unexpected_error_after_the_commit_propagates_with_the_model_restored(started, monkeypatch):
    import stereoseed.sfm.modes

    recon, Ps, cfg, source = started
    before = state(recon)
    monkeypatch.setattr(stereoseed.sfm.modes, "adjust", _raising(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        insert_view(recon, 4, cfg, source)
    assert_same_state(before, state(recon))


def test_a_view_left_without_enough_observations_is_dropped_at_the_end(small_box_scene):
    # a weakly placed view can lose its observations to outlier removal until nothing determines
    # its camera; the finishing step then deregisters it and says why
    from stereoseed.sfm.finishing import _drop_undetermined_views
    from stereoseed.pipeline import reconstruct

    scene = small_box_scene.prefix(5)
    cfg = Config().replace(trust={"keep_flagged": True})  # a flagged view keeps its observations here
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], cfg)
    assert _drop_undetermined_views(recon, cfg.resection) == {}  # a sound run keeps every view
    seen = np.flatnonzero(recon.obs_view == 3)
    cut = np.zeros(len(recon.obs_view), bool)
    cut[seen[5:]] = True  # view 3 keeps 5 observations
    recon.remove_observations(cut)
    dropped = _drop_undetermined_views(recon, cfg.resection)
    assert list(dropped) == [scene.names[3]] and "5 observations" in dropped[scene.names[3]]
    assert recon.views[3].P is None and recon.views[3].status.startswith("failed")
    assert all(recon.views[k].P is not None for k in (0, 1, 2, 4))



def _cannot_follow(monkeypatch, k, after):
    """View k cannot be placed while any of the views ``after`` is registered (as a view placed
    on the wrong copy of a repeated pattern leaves the next nothing to chain to)."""
    import stereoseed.sfm.mapper as mapper
    from stereoseed.sfm.registration.base import RegistrationFailure

    registered = mapper._registered

    def refusing(recon, source, i, cfg):
        if i == k and any(recon.views[v].registered for v in after):
            return RegistrationFailure(f"{recon.views[i].name}: nothing to chain to")
        return registered(recon, source, i, cfg)

    monkeypatch.setattr(mapper, "_registered", refusing)


def _flagged_when_placed(monkeypatch, k):
    """View k's registration says it is ambiguous (as a choice between copies of a pattern)."""
    import dataclasses

    import stereoseed.sfm.mapper as mapper

    registered = mapper._registered

    def flagging(recon, source, i, cfg):
        found = registered(recon, source, i, cfg)
        if i == k and not isinstance(found, mapper.RegistrationFailure):
            found = dataclasses.replace(found, flag=Flag.parse("ambiguous: repeated structure (as if)"))
        return found

    monkeypatch.setattr(mapper, "_registered", flagging)


@pytest.mark.parametrize("flagged", [True, False])
def test_a_flagged_view_the_next_cannot_follow_is_withdrawn(monkeypatch, flagged):
    from stereoseed.geometry.projection import camera_center

    cfg = Config()
    recon, names, Ps, source = walked(7, upto=4, cfg=cfg)
    if flagged:
        recon.flag(4, Flag.parse("ambiguous: repeated structure (as if)"))
    _cannot_follow(monkeypatch, 5, after=(4,))
    before = state(recon)
    report = insert_view(recon, 5, cfg, source)
    if not flagged:  # nothing speaks against view 4: view 5 fails, the model as it was
        assert report["status"] == "failed" and "withdrawn" not in report
        assert_same_state(before, state(recon))
        return
    assert report["status"] == "registered" and list(report["withdrawn"]) == [names[4]]
    assert "flagged when placed (ambiguous: repeated structure" in report["withdrawn"][names[4]]
    assert not recon.views[4].registered and recon.views[4].status.startswith("failed: ")
    assert recon.views[4].placement_flag is None and not np.any(recon.obs_view == 4)
    assert np.linalg.norm(camera_center(recon.views[5].P) - camera_center(Ps[5])) < 0.002


def test_a_view_placed_by_propagated_matches_alone_the_next_cannot_follow_is_withdrawn(monkeypatch):
    # its registration is weak evidence too (the castle from 0008: 0013, placed by propagated
    # matches 0.35 m off, left every later image unplaced)
    from stereoseed.geometry.projection import camera_center
    from stereoseed.sfm.registration.base import FoundBy

    cfg = Config()
    recon, names, Ps, source = walked(7, upto=4, cfg=cfg)
    as_if_placed_by(recon, 4, FoundBy.QUASI_DENSE)
    _cannot_follow(monkeypatch, 5, after=(4,))
    report = insert_view(recon, 5, cfg, source)
    assert report["status"] == "registered" and list(report["withdrawn"]) == [names[4]]
    assert "withdrawn: placed by the propagated matches alone, and the next image" in report["withdrawn"][names[4]]
    assert not recon.views[4].registered and not np.any(recon.obs_view == 4)
    assert np.linalg.norm(camera_center(recon.views[5].P) - camera_center(Ps[5])) < 0.002


def test_a_flagged_view_stays_when_the_next_fails_without_it_too(monkeypatch):
    cfg = Config()
    recon, names, Ps, source = walked(7, upto=4, cfg=cfg)
    recon.flag(4, Flag.parse("ambiguous: repeated structure (as if)"))
    _cannot_follow(monkeypatch, 5, after=(3, 4))
    before = state(recon)
    report = insert_view(recon, 5, cfg, source)
    assert report["status"] == "failed" and "without_flagged_previous" in report
    assert_same_state(before, state(recon))
    assert recon.views[4].registered and recon.views[4].placement_flag


def test_the_report_of_a_withdrawn_view_says_it_failed(monkeypatch):
    # the run's report: the withdrawn view's entry turns failed, with the reason and its kind
    import stereoseed.pipeline as pipeline
    from stereoseed.sfm.registration.base import FailureKind

    images, names, Ps, source = ring(7)
    _flagged_when_placed(monkeypatch, 4)
    _cannot_follow(monkeypatch, 5, after=(4,))
    recon, report = pipeline.reconstruct(images, names, Ps[:2], Config(), source=source)
    entry = report["per_image"][4]
    assert entry["status"] == "failed" and entry["failure"] == FailureKind.WITHDRAWN
    assert entry["reason"].startswith(f"{names[4]}: withdrawn")
    assert report["per_image"][5]["status"] == "registered" and report["registered"] == 6


def test_a_resumed_run_withdraws_a_doubted_view_as_the_uninterrupted_one(monkeypatch, tmp_path):
    # the model before the doubted view's insertion is part of the checkpoint: interrupted just
    # after that view, the resumed run puts it back as the uninterrupted run does (its points,
    # adjustments and outlier removals gone), not only the view's camera and observations
    import stereoseed.pipeline as pipeline

    def untimed(value):
        if isinstance(value, dict):
            return {k: untimed(v) for k, v in value.items() if k != "seconds"}
        return [untimed(v) for v in value] if isinstance(value, list) else value

    _flagged_when_placed(monkeypatch, 4)
    _cannot_follow(monkeypatch, 5, after=(4,))
    images, names, Ps, source = ring(7)
    whole, report = pipeline.reconstruct(images, names, Ps[:2], Config(), source=source)
    checkpoint = tmp_path / "run.npz"

    def interrupt(recon, per_image):
        if len(per_image) == 5:  # view 4 placed, flagged: the model before it is kept
            assert recon.insertion_undo is not None and recon.insertion_undo[0] == 4
            raise KeyboardInterrupt

    images, names, Ps, source = ring(7)
    with pytest.raises(KeyboardInterrupt):
        pipeline.reconstruct(images, names, Ps[:2], Config(), source=source, checkpoint=checkpoint,
                             after_insertion=interrupt)
    images, names, Ps, source = ring(7)
    for i in range(len(images)):  # the exact source knows the interest points it gave (a resume asks for none)
        source.features(i, images[i])
    resumed, again = pipeline.reconstruct(images, names, Ps[:2], Config(), source=source, checkpoint=checkpoint,
                                          resume=True)
    assert again["resumed_images"] == names[:5] and report["per_image"][4]["status"] == "failed"
    assert untimed(again["per_image"]) == untimed(report["per_image"])
    np.testing.assert_array_equal(resumed.live_points()[0], whole.live_points()[0])
    for a, b in zip(resumed.views, whole.views):
        assert a.history == b.history and (a.P is None) == (b.P is None)
        if a.P is not None:
            np.testing.assert_array_equal(a.P, b.P)


def test_a_withdrawal_puts_back_the_model_from_before_the_flagged_view(monkeypatch):
    # the flagged view's points, the adjustments and the outlier removals of its insertion go
    # with it: every point left from then on was made by the next image's insertion
    cfg = Config()
    recon, names, Ps, source = walked(7, upto=4, cfg=cfg)
    n_before = len(recon.points)
    _flagged_when_placed(monkeypatch, 5)
    assert insert_view(recon, 5, cfg, source)["status"] == "registered" and recon.views[5].placement_flag
    assert len(recon.points) > n_before  # view 5 made points of its own
    _cannot_follow(monkeypatch, 6, after=(5,))
    report = insert_view(recon, 6, cfg, source)
    assert report["status"] == "registered" and list(report["withdrawn"]) == [names[5]]
    assert len(recon.points) == n_before + report["new_points"]  # no row of view 5's points left
    later = np.flatnonzero(recon.alive[n_before:]) + n_before
    assert len(later) and all(6 in recon.obs_view[recon.obs_point == p] for p in later)
    assert not np.any(recon.obs_view == 5) and recon.views[5].features is None


def test_an_error_after_a_withdrawal_puts_the_flagged_view_back(monkeypatch):
    import stereoseed.sfm.mapper as mapper

    cfg = Config()
    recon, names, Ps, source = walked(7, upto=4, cfg=cfg)
    recon.flag(4, Flag.parse("ambiguous: repeated structure (as if)"))
    _cannot_follow(monkeypatch, 5, after=(4,))
    before, status = state(recon), recon.views[4].status
    monkeypatch.setattr(mapper, "_commit_and_grow", _raising(np.linalg.LinAlgError("Singular matrix")))
    report = insert_view(recon, 5, cfg, source)
    assert report["status"] == "failed" and f"placed only without {names[4]}" in report["reason"]
    assert_same_state(before, state(recon))
    assert recon.views[4].status == status and recon.views[4].placement_flag


def test_the_view_knows_what_placed_it():
    cfg = Config()
    recon, names, Ps, source = walked(7, upto=3, cfg=cfg)
    assert [recon.views[k].found_by for k in (2, 3)] == ["epipolar chain", "epipolar chain"]
