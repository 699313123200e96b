"""A stereo rig walked live with both cameras (``stereoseed live --watch LEFT --rig RIGHT``): a
station is taken once both its photos are complete, and the result is ``reconstruct --rig``'s on
the same photos."""
from __future__ import annotations

import json
import os
from dataclasses import replace

import cv2
import numpy as np
import pytest

from scene_helpers import write_calib
from stereoseed.api import reconstruct
from stereoseed.errors import StereoseedError
from stereoseed.live import LiveConfig, run_live
from stereoseed.live.watch import RigWatch
from stereoseed.synthetic.rig import RigConfig, render_rig
from stereoseed.synthetic.scene import SceneConfig

FAST = LiveConfig(poll_s=0.05, stable_s=0.1, unreadable_after_s=0.4, heartbeat_s=0.3)


@pytest.fixture(scope="module")
def rig_walk(tmp_path_factory):
    """Three stations of a rendered rig written as each camera names its photos (both sides
    000.png, 001.png, ...): (left folder, right folder, calib.json)."""
    view = replace(SceneConfig(), width=320, height=240, focal_px=400.0, focal0_px=390.0, supersample=1)
    s = render_rig(RigConfig(stations=3, noise_sigma=1.0, view=view)).scene
    folder = tmp_path_factory.mktemp("rig")
    for side, name in ((0, "left"), (1, "right")):
        (folder / name).mkdir()
        for k in range(3):
            cv2.imwrite(str(folder / name / f"{k:03d}.png"), s.images[2 * k + side])
    return folder / "left", folder / "right", write_calib(folder / "calib.json", s.P[:2])


def _cameras(out) -> dict[str, dict]:
    return {c["name"]: c for c in json.loads((out / "cameras.json").read_text())["images"]}


def test_a_rig_walked_live_is_reconstruct_rig_on_the_same_photos(rig_walk, tmp_path):
    left, right, calib = rig_walk
    reconstruct(left, calib, tmp_path / "ref", rig_right=right)
    report = run_live(left, calib, tmp_path / "live", live=FAST, until=6, port=0, rig=right)
    assert report["registered"] == 6 and report["live"]["photos"] == 6
    ref, live = _cameras(tmp_path / "ref"), _cameras(tmp_path / "live")
    # the same names as reconstruct --rig gives (each camera's folder in front), stations and sides
    assert list(live) == list(ref) == ["left_000.png", "right_000.png", "left_001.png", "right_001.png",
                                       "left_002.png", "right_002.png"]
    for name, c in ref.items():
        got = live[name]
        assert (got["station"], got["side"], got["status"], got.get("flag_reason")) == \
               (c["station"], c["side"], c["status"], c.get("flag_reason")), name
        assert np.abs(np.subtract(got["center"], c["center"])).max() <= 1e-9, name
        assert np.abs(np.subtract(got["R"], c["R"])).max() <= 1e-9, name
    inputs = json.loads((tmp_path / "live" / "inputs.json").read_text())["images"]
    assert [(e["side"], e["original_name"]) for e in inputs[:2]] == [("left", "left_000.png"),
                                                                     ("right", "right_000.png")]


def test_a_station_is_taken_once_both_its_photos_are_complete(tmp_path):
    rng = np.random.default_rng(0)
    left, right = tmp_path / "cam0", tmp_path / "cam1"
    left.mkdir(), right.mkdir()
    watch = RigWatch(left, right, FAST)

    def put(folder, name, seconds):
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (20, 30, 3), dtype=np.uint8))
        os.utime(folder / name, ns=(seconds * 10**9, seconds * 10**9))

    put(left, "a.png", 1)
    put(left, "b.png", 2)
    assert not watch.look(0.0).arrivals and not watch.look(1.0).arrivals  # no right photo yet
    put(right, "x.png", 3)
    watch.look(2.0)
    look = watch.look(3.0)
    assert [a.name for a in look.arrivals] == ["cam0_a.png", "cam1_x.png"]  # the first station, left first
    put(right, "y.png", 4)
    watch.look(4.0)
    assert [a.name for a in watch.look(5.0).arrivals] == ["cam0_b.png", "cam1_y.png"]
    # a camera that missed a shot: the left one is two photos ahead, the pair's times 10 s apart
    put(left, "c.png", 5)
    put(left, "d.png", 6)
    put(left, "e.png", 7)
    put(right, "z.png", 17)
    watch.look(6.0)
    look = watch.look(7.0)
    assert [a.name for a in look.arrivals] == ["cam0_c.png", "cam1_z.png"]
    assert any("written 12 s apart" in note and "paired wrong" in note for note in look.notes), look.notes
    assert any("2 photos wait for the other camera's" in note for note in look.notes), look.notes
    with pytest.raises(StereoseedError, match="the same folder for both cameras"):
        RigWatch(left, left, FAST)


def test_a_rig_walk_live_refuses_an_odd_count_and_a_video(rig_walk, tmp_path):
    left, right, calib = rig_walk
    with pytest.raises(StereoseedError, match="give an even number"):
        run_live(left, calib, tmp_path / "o", live=FAST, until=5, port=0, rig=right)
    with pytest.raises(StereoseedError, match="not with --video"):
        run_live(None, calib, tmp_path / "o", live=FAST, port=0, rig=right, video=tmp_path / "walk.mp4")
    assert not (tmp_path / "o").exists()


def test_an_interrupted_rig_walk_resumes_as_a_rig_walk(rig_walk, tmp_path):
    from stereoseed.live.session import LiveRun
    from stereoseed.live.watch import Arrival

    left, right, calib = rig_walk

    def station(k):
        return [Arrival(folder / f"{k:03d}.png", f"{folder.name}_{k:03d}.png", (folder / f"{k:03d}.png").read_bytes(),
                        True, 0.0) for folder in (left, right)]

    run = LiveRun(calib, tmp_path / "live", rig=True)
    run.add(*station(0))
    assert run.add(*station(1))["status"] == "registered"
    run.close()  # stopped without finishing
    with pytest.raises(StereoseedError, match="resume it as it was"):
        LiveRun(calib, tmp_path / "live", resume=True)  # without --rig
    resumed = LiveRun(calib, tmp_path / "live", resume=True, rig=True)
    assert resumed.resumed == ["left_000.png", "right_000.png", "left_001.png", "right_001.png"]
    resumed.add(*station(2))
    resumed.finish()
    reconstruct(left, calib, tmp_path / "ref", rig_right=right)
    ref, live = _cameras(tmp_path / "ref"), _cameras(tmp_path / "live")
    assert list(live) == list(ref)
    for name, c in ref.items():
        assert np.abs(np.subtract(live[name]["center"], c["center"])).max() <= 1e-9, name


def test_a_rig_walk_stopped_between_a_stations_two_photos_resumes_as_reconstruct(rig_walk, tmp_path, monkeypatch):
    """Killed after a station's left image was inserted and before its right one: the checkpoint
    holds the right image as a view not reached yet, which the resumed run inserts first."""
    import stereoseed.live.session as session
    from stereoseed.live.session import LiveRun
    from stereoseed.live.watch import Arrival

    left, right, calib = rig_walk

    def station(k):
        return [Arrival(folder / f"{k:03d}.png", f"{folder.name}_{k:03d}.png", (folder / f"{k:03d}.png").read_bytes(),
                        True, 0.0) for folder in (left, right)]

    insert = session.insert_next

    def dies_at_the_second_right(recon, images, k, *args):
        if k == 3:
            raise KeyboardInterrupt  # the user's Ctrl-C, between the station's two insertions
        return insert(recon, images, k, *args)

    run = LiveRun(calib, tmp_path / "live", rig=True)
    run.add(*station(0))
    monkeypatch.setattr(session, "insert_next", dies_at_the_second_right)
    with pytest.raises(KeyboardInterrupt):
        run.add(*station(1))
    run.close()
    monkeypatch.setattr(session, "insert_next", insert)
    resumed = LiveRun(calib, tmp_path / "live", resume=True, rig=True)
    resumed.add(*station(2))
    resumed.finish()
    reconstruct(left, calib, tmp_path / "ref", rig_right=right)
    ref, live = _cameras(tmp_path / "ref"), _cameras(tmp_path / "live")
    assert list(live) == list(ref) and all(c["registered"] for c in live.values())
    for name, c in ref.items():
        assert np.abs(np.subtract(live[name]["center"], c["center"])).max() <= 1e-9, name


def test_folders_whose_names_could_make_two_photos_one_name_are_left_and_right(tmp_path):
    """cam + b_1.png and cam_b + 1.png would both be cam_b_1.png: the sides are then named left
    and right; a resumed run's photo that neither folder names is one line."""
    (tmp_path / "cam").mkdir(), (tmp_path / "cam_b").mkdir()
    watch = RigWatch(tmp_path / "cam", tmp_path / "cam_b", FAST)
    assert watch.prefixes == ("left", "right") and watch.named(0, "b_1.png") != watch.named(1, "1.png")
    (tmp_path / "cam0").mkdir(), (tmp_path / "cam1").mkdir()
    watch = RigWatch(tmp_path / "cam0", tmp_path / "cam1", FAST)
    assert watch.prefixes == ("cam0", "cam1")
    with pytest.raises(StereoseedError, match="resume with the folders the run watched"):
        watch.mark_taken(["left_000.png"])
