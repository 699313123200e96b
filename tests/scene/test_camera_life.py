"""A camera's life on the model directly: only a placed camera is flagged, a withdrawn or dropped
view leaves no observation, a rollback takes the events back, and the per-image report is
rendered from the history (its values what the report has always said)."""
import json

import numpy as np
import pytest

from geometry_helpers import ring_camera
from stereoseed.features.harris import Features
from stereoseed.geometry.camera import Camera
from stereoseed.scene.camera_life import (Flag, FlagKind, Inserted, Registered, Stage, Withdrawn, event_from_json,
                                          event_to_json, report_of)
from stereoseed.scene.reconstruction import Reconstruction, View

AMBIGUOUS = Flag.parse("ambiguous: repeated structure (as if)")


def _model(n_views=4, n_features=10):
    """Views 0 and 1 calibrated, view 2 registered by the motion prior with its report; view 3
    pending; two points seen by views 0-2."""
    views = []
    for i in range(n_views):
        f = Features(np.random.default_rng(i).uniform(0, 600, (n_features, 2)), np.zeros((n_features, 1), np.float32),
                     np.ones(n_features, bool), np.ones(n_features), (480, 640))
        views.append(View(f"v{i}", features=f, point_of_feature=np.full(n_features, -1, np.int64),
                          image=np.zeros((480, 640, 3), np.uint8)))
    recon = Reconstruction(views)
    for i in (0, 1):
        recon.calibrate(i, ring_camera(20.0 * i)[3])
        recon.record(i, {"image": f"v{i}", "status": "calibrated"})
    recon.register(2, Camera(ring_camera(40.0)[3]), "motion prior", views[2].features, views[2].image, False, None,
                   True)
    ids = recon.add_points(np.ones((2, 3)), np.zeros((2, 3)))
    for v in range(3):
        recon.add_observations(v, [0, 1], ids)
    recon.record(2, {"image": "v2", "matches": 31, "registered_by": "motion prior", "status": "registered"})
    return recon


def test_only_a_placed_camera_is_flagged_and_a_pending_one_fails():
    recon = _model()
    with pytest.raises(ValueError, match="only a placed camera"):
        recon.flag(3, AMBIGUOUS)
    with pytest.raises(ValueError, match="withdrawn or dropped, not failed"):
        recon.fail(2, "why", {})
    with pytest.raises(ValueError, match="only a registered camera is withdrawn"):
        recon.withdraw(0, "the calibrated pair is the frame")
    recon.fail(3, "v3: too few matches", {"image": "v3", "status": "failed", "reason": "v3: too few matches"})
    assert recon.views[3].status == "failed: v3: too few matches" and not recon.views[3].registered


def test_a_flag_raised_when_placed_stands_until_judged_or_lifted():
    recon = _model()
    view = recon.views[2]
    assert view.reliable and view.found_by == "motion prior" and view.status == "registered"
    recon.flag(2, AMBIGUOUS)
    assert view.placement_flag == AMBIGUOUS and view.flag_reason == "ambiguous: repeated structure (as if)"
    recon.judge(2, None)  # the final judgement speaks for the camera now; its registration's flag is kept
    assert view.reliable and view.placement_flag == AMBIGUOUS
    recon.lift_flag(2, "the propagated matches decide")
    assert view.placement_flag is None and view.flag is None


def test_a_withdrawn_view_leaves_no_observation_and_its_report_says_why():
    recon = _model()
    recon.flag(2, AMBIGUOUS)
    recon.withdraw(2, "v2: withdrawn: flagged when placed, and the next image was placed only without it")
    view = recon.views[2]
    assert not view.registered and not np.any(recon.obs_view == 2) and view.features is None
    assert view.status.startswith("failed: v2: withdrawn") and view.placement_flag is None and view.found_by is None
    assert [type(e).__name__ for e in view.history] == ["Registered", "Inserted", "Flagged", "Withdrawn"]
    assert recon.track_lengths().tolist() == [2, 2]
    report = recon.reports()[2]
    assert report == {"image": "v2", "status": "failed", "reason": view.life.reason,
                      "failure": "withdrawn after the next image",
                      "withdrawn_registration": {"matches": 31, "registered_by": "motion prior"}}


def test_a_withdrawal_puts_back_the_model_as_before_the_insertion_when_kept():
    recon = _model()
    before = recon.checkpoint()
    ids = recon.add_points(np.zeros((3, 3)), np.zeros((3, 3)))  # what the insertion of view 3 added
    recon.register(3, Camera(ring_camera(60.0)[3]), "quasi-dense", recon.views[3].features, recon.views[3].image,
                   False, None, False)
    recon.add_observations(3, [0, 1, 2], ids)
    recon.add_observations(2, [2, 3, 4], ids)
    recon.record(3, {"image": "v3", "status": "registered"})
    recon.withdraw(3, "v3: withdrawn", before)
    assert len(recon.points) == 2 and recon.views[2].point_of_feature[2:5].tolist() == [-1, -1, -1]
    assert [type(e).__name__ for e in recon.views[3].history] == ["Registered", "Inserted", "Withdrawn"]


def test_a_withdrawal_keeps_the_failures_of_the_views_tried_after_it():
    # view 3 placed (doubted), view 4 failed after it, view 5 placed only without it: the model
    # goes back to before 3's insertion, 4's failure stays (the castle walked back from a JPEG
    # q90 copy: its report ended at the withdrawn view, 4 of 19 images)
    recon = _model(n_views=6)
    before = recon.checkpoint()
    recon.register(3, Camera(ring_camera(60.0)[3]), "quasi-dense", recon.views[3].features, recon.views[3].image,
                   False, None, False)
    recon.record(3, {"image": "v3", "status": "registered"})
    recon.fail(4, "v4: too few matches", {"image": "v4", "status": "failed", "reason": "v4: too few matches"})
    recon.withdraw(3, "v3: withdrawn", before)
    assert recon.views[4].status == "failed: v4: too few matches"
    assert [r["image"] for r in recon.reports()] == ["v0", "v1", "v2", "v3", "v4"]
    assert recon.reports()[4]["reason"] == "v4: too few matches" and recon.reports()[3]["status"] == "failed"


def test_registered_again_and_dropped_are_rendered_over_the_first_registration():
    recon = _model()
    recon.flag(2, AMBIGUOUS)
    recon.register_again(2, "a camera 3.7 away ...")
    view = recon.views[2]
    assert view.found_by == "between its neighbours" and view.placement_flag is None and not view.zoomed
    assert recon.reports()[2] == {"image": "v2", "status": "registered", "registered_by": "between its neighbours",
                                  "registered_again": "a camera 3.7 away ...",
                                  "first_registration": {"matches": 31, "registered_by": "motion prior"}}
    recon.drop(2, "v2: dropped at the end")
    assert not np.any(recon.obs_view == 2) and recon.views[2].status == "failed: v2: dropped at the end"
    assert recon.reports()[2]["status"] == "failed" and recon.reports()[2]["reason"] == "v2: dropped at the end"


def test_a_rollback_takes_the_events_back():
    # an insertion that fails after its commit is rolled back: the flag its registration raised goes too
    recon = _model()
    before = recon.checkpoint()
    recon.flag(2, AMBIGUOUS)
    recon.restore(before)
    assert recon.views[2].placement_flag is None and recon.views[2].flag_reason is None
    assert [type(e).__name__ for e in recon.views[2].history] == ["Registered", "Inserted"]


def test_flags_and_events_read_back_from_their_text():
    for reason in ("ambiguous: repeated structure (the best camera explains 96 recent points, ...)",
                   "weak: only 0 of its observations are of points two other cameras also see",
                   "uncertain: 1-sigma position 0.3 (2.0 % of its distance to the scene, limit 1.0 %)"):
        assert Flag.parse(reason).reason == reason
    assert Flag.parse("contradicted by the other cameras: its 80 observations").kind == FlagKind.CONTRADICTED
    with pytest.raises(ValueError):
        Flag.parse("blurred: not a kind")
    assert AMBIGUOUS.through("v4").reason == "ambiguous: repeated structure (as if) (its station's v4)"
    recon = _model()
    recon.flag(2, AMBIGUOUS, Stage.PLACED)
    recon.withdraw(2, "v2: withdrawn")
    history = recon.views[2].history
    again = tuple(event_from_json(json.loads(json.dumps(event_to_json(e)))) for e in history)
    assert again == history and report_of(again) == report_of(history)
    for bad in ({"event": "Registered"}, {"event": "Pickle", "found_by": "x"}, {"event": "Withdrawn", "reason": 3},
                {"event": "Inserted", "report": []}, "Registered"):
        with pytest.raises(ValueError):
            event_from_json(bad)


def test_a_view_not_reached_has_no_report_and_the_reports_are_a_prefix():
    assert report_of((Registered("epipolar chain"),)) is None
    assert report_of((Inserted({"image": "a", "status": "registered"}), Withdrawn("a: out"))) == {
        "image": "a", "status": "failed", "reason": "a: out", "failure": "withdrawn after the next image",
        "withdrawn_registration": {}}
    assert [r["image"] for r in _model().reports()] == ["v0", "v1", "v2"]
