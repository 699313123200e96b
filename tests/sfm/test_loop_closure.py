"""Loop closure: a closed ring merges the points reconstructed twice."""

from ring_helpers import ring, centre_errors
from stereoseed.config import Config
from stereoseed.sfm.mapper import finish, initialise, insert_view


def test_a_closed_ring_merges_the_points_reconstructed_twice():
    images, names, Ps, source = ring(18)  # 18 x 20 degrees: back to the start
    recon, report = reconstruct_ring(images, names, Ps, source)
    closure = report["loop_closure"]
    assert closure["closed"] and closure["merges"] > 100 and closure["links"] > 0
    pts, _ = recon.live_points()
    # after merging, no physical point is there twice (exact correspondences: twins lie < 2 mm apart)
    from scipy.spatial import cKDTree
    assert len(cKDTree(pts).query_pairs(0.0005)) < 0.01 * len(pts)
    assert centre_errors(recon, Ps).max() < 0.002


def reconstruct_ring(images, names, Ps, source):
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in range(2, len(images)):
        assert insert_view(recon, k, cfg, source)["status"] == "registered"
    return recon, finish(recon, cfg, source)


def test_links_without_a_merge_are_not_a_closed_loop(monkeypatch, caplog):
    # the two ends see each other's points but none is found where the model puts it (as after a
    # wrong camera on the way): a warning, not "closed"
    import stereoseed.sfm.loop_closure as lc

    images, names, Ps, source = ring(18)
    monkeypatch.setattr(lc, "_merge_twins", lambda *args: 0)
    with caplog.at_level("INFO", logger="stereoseed"):
        recon, report = reconstruct_ring(images, names, Ps, source)
    closure = report["loop_closure"]
    assert closure["links"] > 0 and closure["merges"] == 0 and not closure["closed"]
    assert "no point merged" in closure["reason"] and "no point merged" in caplog.text
