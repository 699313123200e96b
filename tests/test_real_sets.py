"""The real walks with ground truth in ../shared/data (skipped, with the reason, where absent):
every camera is right or flagged, with the figures benchmarks/bench_real.py prints for `make bench`."""
import sys
from pathlib import Path

import pytest

from stereoseed.config import Config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_real  # noqa: E402
import bench_walks  # noqa: E402


def _run(walk, cfg=Config()):
    """bench_real's figures of ``walk``; skipped (with bench_real's reason) where its data is absent."""
    r = bench_real.run_walk(walk, cfg)  # $STEREOSEED_DATA, else ../shared/data
    if "skipped" in r:
        pytest.skip(r["skipped"])
    return r


def _by_image(r):
    return {e["image"]: e for e in r["per_image"]}


def _right_or_flagged(r, pct=1.0):
    """Every camera more than ``pct`` % of the distance off is flagged."""
    return all(e.get("centre_error_pct", 0) <= pct or "flag" in e for e in r["per_image"])


def test_castle_cameras_a_window_period_off_are_registered_again_between_their_neighbours():
    # the courtyard's repeated windows: 0008 and 0016 are matched one period over, metres off, and
    # flagged ambiguous at their registration; after the final BA the cameras their neighbours
    # find between them, the true ones, take their places
    r = _run(bench_real.SETS["strechaCastleP19"])
    assert r["registered"] == 19
    entry = _by_image(r)
    for name in ("0008.jpg", "0016.jpg"):
        assert entry[name]["registered_by"] == "between its neighbours" and "flag" not in entry[name]
        assert "repeated structure" in entry[name]["first_registration"]["flag"]
    # every camera more than 1 % of the distance off is flagged; the unflagged median within 0.2 %
    assert _right_or_flagged(r)
    # all 19 placed (0018's rival camera, 1.2 m over, is told apart by the propagated matches'
    # epipolar geometry), all unflagged but the last, 0018: the motion prior's, with no camera
    # after it to confirm it (trust.unconfirmed_cameras; 27 mm, 0.06 % off)
    assert r["unflagged"]["median_pct"] < 0.2 and r["unflagged"]["count"] == 16
    assert "no later camera confirms it" in entry["0018.jpg"]["flag"]


def test_fountain_is_placed_to_a_tenth_of_a_percent():
    r = _run(bench_real.SETS["strechaFountainP11"])
    assert r["registered"] == 11 and r["unflagged"]["count"] == 9
    assert r["unflagged"]["median_pct"] < 0.1 and r["unflagged"]["worst_pct"] < 0.15


def test_weak_texture_zooms_the_window_cannot_measure_are_refused():
    # dinoRing1-24 every 2nd view (the lens never zoomed): a 1 % zoom taken on the first insertion
    # drifted the walk by 37 mm; zooms of 4-24 % that the view measures to 1-2 % are not taken
    r = _run(bench_real.SETS["dinoRing1-24/2"])
    # (dino0019, the motion prior's, is flagged weak: the two after it are flagged themselves, so
    # nothing confirms it; 1.3 mm off)
    assert r["registered"] == 12 and r["unflagged"]["count"] >= 7
    assert r["unflagged"]["median"] < 0.002 and r["unflagged"]["worst"] < 0.005
    third = _run(bench_real.SETS["dinoRing1-24/3"])
    # every 3rd view: 0022, registered on quasi-dense matches 8 mm off, keeps 22 observations of
    # points two other cameras see and is flagged weak
    assert third["unflagged"]["count"] >= 4 and third["unflagged"]["median"] < 0.002
    assert third["unflagged"]["worst"] < 0.005


def test_dino_sparse_ring_and_temple_keep_their_millimetre(temple_run):
    dino = _run(bench_real.SETS["dinoSparseRing"])
    # (dinoSR0006, the motion prior's, the last placed: the two after it fail, nothing confirms it)
    assert dino["unflagged"]["count"] >= 11 and dino["unflagged"]["worst"] < 0.005
    recon, report, truth = temple_run  # the session's temple walk: the set's own run, as bench_real does it
    temple = bench_real.set_figures(recon, report, {v.name: P for v, P in zip(recon.views, truth)})
    assert temple["registered"] == 16 and temple["unflagged"]["median"] < 0.0015


def test_the_castle_walked_backwards_goes_on_past_a_wrong_copy_of_its_windows():
    # walked the other way round, 0015 is placed on the wrong copy of the windows (2.2 m off,
    # flagged) and 0014 cannot follow it: 0015 is withdrawn and the walk goes on from 0016
    # (before: every image after 0015 failed, 3 of 19 placed). 0007 then chains to only 24 of
    # its 43 pairs, a camera 4.7 m off: a chain split so is not trusted without the motion prior
    r = _run(bench_walks.WALKS["strechaCastleP19 backwards"])
    entry = _by_image(r)
    assert entry["0015.jpg"]["status"] == "failed" and "withdrawn" in entry["0015.jpg"]["reason"]
    assert r["placed"]["count"] >= 15
    assert _right_or_flagged(r, 1.5)
    assert r["unflagged"]["median_pct"] < 0.8


def test_a_part_of_the_walk_resting_on_a_flagged_camera_is_flagged():
    # dinoSparseRing walked back from its 12th image: 0013 is flagged at its registration (a zoom
    # it cannot measure), and the four cameras after it, placed on its matches, share at most 2
    # points seen by three cameras with the rest once it leaves the model: 15-34 mm off and
    # unflagged before, they are flagged now
    r = _run(bench_walks.WALKS["dinoSparseRing backwards from its 12th"])
    entry = _by_image(r)
    for name in ("dinoSR0012.png", "dinoSR0011.png", "dinoSR0010.png", "dinoSR0009.png"):
        # weak (not tied to the pair, or too few ties to check) or uncertain: flagged either way
        assert entry[name].get("flag", "").startswith(("weak: ", "uncertain: ")), entry[name]
    assert _right_or_flagged(r)
    assert r["unflagged"]["count"] >= 5 and r["unflagged"]["worst"] < 0.005


def test_a_view_placed_by_propagated_matches_the_next_cannot_follow_is_withdrawn():
    # the castle walked from 0008: 0013, placed by the propagated matches alone 0.35 m off, left
    # every later image unplaced (6 of 11 placed); withdrawn, the walk goes on from 0012
    r = _run(bench_walks.WALKS["strechaCastleP19 from 0008"])
    entry = _by_image(r)
    assert entry["0013.jpg"]["status"] == "failed" and "placed by the propagated matches alone" in entry["0013.jpg"]["reason"]
    # (the last, 0018, the motion prior's with nothing after it, is flagged weak: 0.2 % off)
    assert r["registered"] >= 10 and r["unflagged"]["count"] >= 7
    assert _right_or_flagged(r)


def test_a_camera_its_neighbours_place_elsewhere_is_registered_again():
    # the castle walked from 0010: 0016, placed by the motion prior on the wrong copy of the
    # windows 3.7 m off, explains 150 of its neighbours' points; the camera found between 0015
    # and 0017, the true one, 275, and takes its place
    r = _run(bench_walks.WALKS["strechaCastleP19 from 0010"])
    entry = _by_image(r)["0016.jpg"]
    assert entry["registered_by"] == "between its neighbours" and entry["centre_error_pct"] < 1
    assert entry["first_registration"]["registered_by"] == "motion prior"
    assert _right_or_flagged(r)
    assert r["unflagged"]["count"] >= 6
    # (without that judgement, 3.7 m off, it was flagged uncertain by its sigma alone, 2026-12-07;
    # no longer re-run here: the suite's five minutes)
