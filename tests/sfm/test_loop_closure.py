"""Loop closure: a closed ring merges the points reconstructed twice, and the loop is called
closed only when the gap measured between its ends is within what the cameras measure."""
import copy

import numpy as np
import pytest

from ring_helpers import centre_errors, walked
from stereoseed.config import Config
from stereoseed.sfm.loop_closure import CLOSED, NOT_A_LOOP, NOT_CLOSED, NOT_SEEN, describe_loop
from stereoseed.sfm.mapper import finish


@pytest.fixture(scope="module")
def walked_ring():
    """18 x 20 degrees, every view inserted, not finished: back to the start."""
    return walked(18)


def finished(walked_ring, wrong_last_by=None):
    """A copy of the walked ring finished (loop closure, trust); ``wrong_last_by``: the last
    camera moved first by that much along its own x axis (its rotation kept)."""
    recon, names, Ps, source = copy.deepcopy(walked_ring)
    if wrong_last_by is not None:
        v = recon.views[recon.registered_views[-1]]
        centre = v.center + wrong_last_by * v.R[0]
        v.P = v.K @ np.hstack([v.R, (-v.R @ centre)[:, None]])
    return recon, Ps, finish(recon, Config(), source)


def test_a_closed_ring_merges_the_points_reconstructed_twice(walked_ring):
    recon, Ps, report = finished(walked_ring)
    closure = report["loop_closure"]
    assert closure["closed"] and closure["merges"] > 100 and closure["links"] > 0
    pts, _ = recon.live_points()
    # after merging, no physical point is there twice (exact correspondences: twins lie < 2 mm apart)
    from scipy.spatial import cKDTree
    assert len(cKDTree(pts).query_pairs(0.0005)) < 0.01 * len(pts)
    assert centre_errors(recon, Ps).max() < 0.002
    # the gap measured before the closing BA: within what the cameras measure, as a share of the loop
    assert closure["verdict"] == CLOSED and 0 < closure["gap"] <= closure["gap_sigmas"] * closure["uncertainty"]
    assert closure["uncertainty"] < 0.001 and closure["points"] >= Config().loop_closure.min_gap_points
    assert closure["loop_length"] > 5 and closure["gap_percent"] == pytest.approx(
        100 * closure["gap"] / closure["loop_length"])
    assert describe_loop(closure).startswith("closed: gap ")


def test_ends_sharing_no_reconstructed_point_close_on_their_gap(walked_ring, monkeypatch):
    # templeSparseRing's case: the last views link the first views' points but no point was
    # reconstructed at both ends (no merge); the gap, measured on those points, shows the ends meet
    import stereoseed.sfm.loop_closure as lc

    monkeypatch.setattr(lc, "_merge_twins", lambda *args: 0)
    _, _, report = finished(walked_ring)
    closure = report["loop_closure"]
    assert closure["links"] > 0 and closure["merges"] == 0
    assert closure["closed"] and closure["gap"] <= closure["gap_sigmas"] * closure["uncertainty"]


def test_a_wrong_last_camera_is_not_a_closed_loop_and_its_gap_is_said(walked_ring, monkeypatch, caplog):
    # a camera one period over (a facade's windows: links made within a few pixels, no merge, a
    # camera metres off) must not be called closed, even though the other end views link
    import stereoseed.sfm.loop_closure as lc

    monkeypatch.setattr(lc, "_merge_twins", lambda *args: 0)
    with caplog.at_level("INFO", logger="stereoseed"):
        _, _, report = finished(walked_ring, wrong_last_by=0.05)
    closure = report["loop_closure"]
    assert closure["links"] > 0 and not closure["closed"] and closure["verdict"] == NOT_CLOSED
    assert closure["ends"][0] == "v17.png"  # the worst pair: the moved camera's
    assert 0.03 < closure["gap"] < 0.06 and closure["gap"] > 10 * closure["uncertainty"]
    text = describe_loop(closure)
    assert text.startswith("not closed: gap 0.0") and "% of the loop" in text and "beyond what the cameras measure" in text
    assert "not closed: gap" in caplog.text


def test_ends_sharing_too_few_points_are_not_judged(walked_ring):
    # a ring whose ends share fewer points than a gap needs: neither closed nor a failure
    recon, _, _, source = copy.deepcopy(walked_ring)
    closure = finish(recon, Config().replace(loop_closure={"min_gap_points": 10 ** 6}), source)["loop_closure"]
    assert not closure["closed"] and closure["verdict"] == NOT_SEEN and "gap" not in closure
    assert describe_loop(closure).startswith("ends not seen together (only 1821 points measured")


def test_an_open_walk_is_not_called_closed():
    # nine views 8 degrees apart: the ends see the same side of the box, but never parted
    recon, _, _, source = walked(9, step_deg=8.0)
    closure = finish(recon, Config(), source)["loop_closure"]
    assert not closure["closed"] and closure["verdict"] == NOT_A_LOOP
    assert "not a loop" in describe_loop(closure)


def test_the_words_of_each_verdict():
    mm = lambda x: f"{x * 1000:.3g} mm"  # noqa: E731
    judged = {"gap": 0.0012, "gap_percent": 0.037, "uncertainty": 0.0005, "gap_sigmas": 3.0, "ends": ["a", "b"]}
    assert describe_loop({**judged, "verdict": CLOSED, "closed": True}, mm) == \
        "closed: gap 1.2 mm (0.037 % of the loop), within 3 × its 1-sigma 0.5 mm"
    assert describe_loop({**judged, "verdict": NOT_CLOSED, "closed": False}, mm).startswith(
        "not closed: gap 1.2 mm (0.037 % of the loop), beyond what the cameras measure (3 × its 1-sigma 0.5 mm)")
    assert describe_loop({"verdict": "ends not seen together", "reason": "only 3 points"}) == \
        "ends not seen together (only 3 points)"
    assert describe_loop({"closed": False, "reason": "old"}) == "not closed (old)"  # a report from before


def test_the_report_page_puts_only_a_real_failure_in_bold():
    from stereoseed.output.report.html import _loop_text

    judged = {"gap": 0.0012, "gap_percent": 0.037, "uncertainty": 0.0005, "gap_sigmas": 3.0, "ends": ["a", "b"]}
    failed = _loop_text({**judged, "verdict": NOT_CLOSED, "closed": False}, "m")
    assert failed.startswith("not closed: gap 1.2 mm") and "font-weight:normal" not in failed
    for verdict in (CLOSED, NOT_A_LOOP):
        assert "font-weight:normal" in _loop_text({**judged, "verdict": verdict, "closed": verdict == CLOSED}, "m")
