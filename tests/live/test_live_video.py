"""``stereoseed live --video``: the keyframes reconstruct picks, at the stream's pace through a
bounded queue; with no frame dropped the result is reconstruct's on the pair and the video."""
from __future__ import annotations

import json
import time

import pytest

from scene_helpers import write_calib, write_video
from stereoseed.io.files import write_image
from stereoseed.io.video import read_keyframes
from stereoseed.live import LiveConfig, run_live
from stereoseed.live.video import VideoFeed
from stereoseed.pipeline import reconstruct_to_folder
from stereoseed.synthetic.scene import SceneConfig, render_scene

SMALL = dict(width=320, height=240, supersample=1, seed=4)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The calibrated pair's two photos, calib.json, and a video walking on from the second
    camera at 2 degrees a frame (as tests/io/test_video.py's, shorter)."""
    folder = tmp_path_factory.mktemp("walk")
    pair = render_scene(SceneConfig(n_images=2, focal_px=400, focal0_px=390, principal_offset0_px=(1.5, -1.0), **SMALL))
    frames = render_scene(SceneConfig(n_images=36, step_deg=2.0, azimuth0_deg=50.0, focal_px=400, focal0_px=400,
                                      principal_offset0_px=(0.0, 0.0), focal_jitter=0.0, pose_jitter=False, **SMALL))
    photos = [write_image(folder / f"pair{i}.png", image) for i, image in enumerate(pair.images)]
    return photos, write_calib(folder / "calib.json", pair.P[:2]), write_video(folder / "walk.avi", frames.images)


def _cameras(out):
    return {c["name"]: c for c in json.loads((out / "cameras.json").read_text())["images"]}


def test_a_video_run_live_is_reconstructs_on_the_pair_and_the_video(walk, tmp_path):
    photos, calib, video = walk
    lines = []
    report = run_live(None, calib, tmp_path / "live", video=video, pair=photos, port=0, realtime=False,
                      on_line=lines.append)
    reconstruct_to_folder([str(photos[0]), str(photos[1]), str(video)], str(calib), tmp_path / "ref")
    live, ref = _cameras(tmp_path / "live"), _cameras(tmp_path / "ref")
    assert list(live) == list(ref) and len(ref) >= 5  # the pair, then the same keyframes
    for name, c in ref.items():
        assert (live[name]["status"], live[name].get("flag_reason")) == (c["status"], c.get("flag_reason")), name
        if c["registered"]:
            assert max(abs(a - b) for a, b in zip(live[name]["center"], c["center"])) <= 1e-9, name
    assert report["registered"] == sum(c["registered"] for c in ref.values())
    assert any("the stream ended after 36 frames" in line for line in lines), lines


def test_a_run_that_falls_behind_drops_frames_and_says_so(walk):
    _, _, video = walk
    all_keyframes = [k.name for k in read_keyframes(video)]
    feed = VideoFeed(video, live=LiveConfig(video_queue=1)).start()
    try:
        time.sleep(1.25)  # the run busy: a keyframe waits in the queue, the next one waits, the stream goes on
        taken, notes = [], []
        while not feed.done:
            look = feed.look(time.monotonic())
            taken += [a.name for a in look.arrivals]
            notes += look.notes
            time.sleep(0.02)
        look = feed.look(time.monotonic())
        taken += [a.name for a in look.arrivals]
        notes += look.notes
    finally:
        feed.close()
    assert feed.dropped > 0 and feed.frames + feed.dropped == 36
    assert any("dropped while the run was behind" in n for n in notes), notes
    assert any("the stream ended after 36 frames" in n for n in notes), notes
    assert taken and len(taken) <= len(all_keyframes) + 1  # keyframes still, the queue never longer than one


def test_a_stream_is_read_live_and_its_keyframes_named_after_it_and_the_time(walk, tmp_path):
    """``--video URL`` (a camera's number works alike: OpenCV opens either): the walk served over
    HTTP on 127.0.0.1 gives the keyframes the file gives, named after the stream and the time its
    reading started (a stream cannot be read again: a resumed run's keyframes never take the
    interrupted run's names); a camera or an address that does not answer is one line."""
    import functools
    import http.server
    import re
    import threading

    from stereoseed.errors import StereoseedError

    photos, calib, video = walk
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(video.parent))
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/{video.name}"
        report = run_live(None, calib, tmp_path / "live", video=url, pair=photos, port=0, realtime=False)
    finally:
        server.shutdown()
    names = list(_cameras(tmp_path / "live"))
    from_file = [k.name.split("_")[-1] for k in read_keyframes(video)]
    assert [n.split("_")[-1] for n in names[2:]] == from_file and len(from_file) >= 3
    assert all(re.fullmatch(r"walk_\d{8}-\d{6}_\d{6}\.png", n) for n in names[2:]), names
    assert report["registered"] >= 5
    with pytest.raises(StereoseedError, match="no such camera"):
        VideoFeed("97")
    with pytest.raises(StereoseedError, match="the stream does not answer"):
        VideoFeed("http://127.0.0.1:9/none.mp4")


def test_a_camera_is_read_as_it_delivers_and_a_hiccup_is_not_the_end(walk, monkeypatch):
    """A camera paces itself: a slow first frame, or fewer frames a second than it reports, must
    not make the reader take every later frame for a late one (it would drop them all); one
    failed read in the middle is waited over (LiveConfig.stream_gap_s), not taken for the end."""
    import numpy as np

    import stereoseed.live.video as video

    frames = [np.full((240, 320, 3), 40 + i, np.uint8) for i in range(30)]

    class Camera:  # 20 frames a second after a 0.3 s start, reporting 25; frame 12's read fails once
        def __init__(self, source):
            self.i, self.failed = 0, False

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return True

        def get(self, prop):
            return 25.0

        def read(self):
            time.sleep(0.3 if self.i == 0 else 0.05)
            if self.i == 12 and not self.failed:
                self.failed = True
                return False, None
            if self.i >= len(frames):
                return False, None
            self.i += 1
            return True, frames[self.i - 1]

        def grab(self):
            return self.read()[0]

        def release(self):
            pass

    monkeypatch.setattr(video.cv2, "VideoCapture", Camera)
    feed = VideoFeed("0", live=LiveConfig(stream_gap_s=0.5)).start()  # realtime, as the command reads it
    deadline = time.monotonic() + 30
    while not feed.done and time.monotonic() < deadline:
        feed.look(time.monotonic())
        time.sleep(0.05)
    feed.close()
    assert feed.frames == 30 and feed.dropped == 0
