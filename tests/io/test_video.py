"""Keyframes of a filmed walk (stereoseed.io.video): a synthetic walk at 2 degrees a frame,
written as an MJPG video, becomes keyframes that the mapper places after a calibrated pair."""
import numpy as np
import pytest

from stereoseed.config import Config, VideoConfig
from stereoseed.errors import StereoseedError
from stereoseed.experiments.evaluation import camera_errors
from stereoseed.pipeline import reconstruct
from stereoseed.synthetic.scene import SceneConfig, render_scene
from stereoseed.io.video import read_keyframes
from scene_helpers import write_video

SMALL = dict(width=320, height=240, supersample=1, seed=4)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The calibrated pair (two photos, the second camera at azimuth 50 degrees) and a video
    that walks on from there, 2 degrees a frame, with the second camera (no zoom)."""
    pair = render_scene(SceneConfig(n_images=2, focal_px=400, focal0_px=390, principal_offset0_px=(1.5, -1.0), **SMALL))
    frames = render_scene(SceneConfig(n_images=90, step_deg=2.0, azimuth0_deg=50.0, focal_px=400, focal0_px=400,
                                      principal_offset0_px=(0.0, 0.0), focal_jitter=0.0, pose_jitter=False, **SMALL))
    path = tmp_path_factory.mktemp("video") / "walk.avi"
    write_video(path, frames.images)
    return pair, frames, path


def test_keyframes_are_spaced_by_the_motion_and_start_past_the_first_frame(walk):
    _, frames, path = walk
    keyframes = read_keyframes(path)
    index = np.array([k.index for k in keyframes])
    assert index[0] > 0  # the first frame is where the second calibrated camera stood
    assert np.all(np.diff(index) > 0)
    # 178 degrees walked; a keyframe per ~8 % of the width moved: steps of 10-30 degrees
    steps = np.diff(np.r_[0, index]) * 2.0
    assert 5 <= len(keyframes) <= 12 and steps.min() >= 10 and steps.max() <= 30, steps
    assert keyframes[0].image.shape == frames.images[0].shape
    assert keyframes[0].name == f"walk_{index[0]:06d}.png"
    # a smaller motion threshold gives more keyframes
    assert len(read_keyframes(path, VideoConfig(keyframe_motion=0.04))) > 1.5 * len(keyframes)


def test_keyframes_written_out_are_not_held(walk, tmp_path):
    from stereoseed.io.files import read_image

    _, _, path = walk
    in_memory = read_keyframes(path)
    on_disk = read_keyframes(path, save_to=tmp_path / "keyframes")
    assert [k.name for k in on_disk] == [k.name for k in in_memory]
    assert all(k.image is None and k.path == tmp_path / "keyframes" / k.name for k in on_disk)
    for a, b in zip(on_disk, in_memory):  # PNG: the same pixels
        np.testing.assert_array_equal(read_image(a.entry), b.entry)


def test_two_videos_of_one_name_are_refused(walk, tmp_path):
    # their keyframes would be named, and written, alike
    import shutil

    from stereoseed.errors import StereoseedError
    from stereoseed.io.files import write_image, write_json
    from stereoseed.pipeline import load_sequence

    pair, _, path = walk
    for name, image in zip(("pair0.png", "pair1.png"), pair.images):
        write_image(tmp_path / name, image)
    write_json(tmp_path / "calib.json", {"cameras": [{"P": P.tolist()} for P in pair.P]})
    (tmp_path / "again").mkdir()
    twin = shutil.copy(path, tmp_path / "again" / path.name)
    sources = [str(tmp_path / "pair0.png"), str(tmp_path / "pair1.png"), str(path), str(twin)]
    with pytest.raises(StereoseedError, match="second video named"):
        load_sequence(sources, str(tmp_path / "calib.json"), keyframes_to=tmp_path / "keyframes")


def test_the_keyframes_are_placed_after_the_calibrated_pair(walk):
    pair, frames, path = walk
    keyframes = read_keyframes(path)
    images = list(pair.images) + [k.image for k in keyframes]
    names = list(pair.names) + [k.name for k in keyframes]
    recon, report = reconstruct(images, names, pair.P[:2], Config())
    assert report["registered"] == len(images)
    truth = list(pair.P) + [frames.P[k.index] for k in keyframes]
    err = np.array(camera_errors([v.P_input for v in recon.views], truth)["center_m"][2:])
    assert err.max() < 0.01  # metres, at 1.4 m, 320x240 MJPG frames (measured 0.2-0.3 cm)


def test_a_still_camera_or_a_broken_file_is_refused(tmp_path, walk):
    _, frames, _ = walk
    still = tmp_path / "still.avi"
    write_video(still, [frames.images[0]] * 20)
    with pytest.raises(StereoseedError, match="no keyframe"):
        read_keyframes(still)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00" * 1000)
    with pytest.raises(StereoseedError, match="broken.mp4"):
        read_keyframes(broken)
    with pytest.raises(StereoseedError, match="not found"):
        read_keyframes(tmp_path / "missing.mp4")


def test_reconstruct_takes_the_pair_then_the_video(walk, tmp_path, capsys):
    import json

    from stereoseed.cli import main
    from stereoseed.io.files import write_image, write_json

    pair, frames, video = walk
    for name, image in zip(("pair0.png", "pair1.png"), pair.images):
        write_image(tmp_path / name, image)
    write_json(tmp_path / "calib.json", {"cameras": [{"P": P.tolist()} for P in pair.P]})
    code = main(["reconstruct", str(tmp_path / "pair0.png"), str(tmp_path / "pair1.png"), str(video),
                 "--calib", str(tmp_path / "calib.json"), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 0, capsys.readouterr().err
    keyframes = sorted(p.name for p in (tmp_path / "out" / "keyframes").iterdir())
    assert keyframes == [k.name for k in read_keyframes(video)]  # kept with the result that names them
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["registered"] == report["images"] == 2 + len(keyframes)
    # the result records its keyframes as its own files, the pair beside it (what the hand-offs read)
    inputs = json.loads((tmp_path / "out" / "inputs.json").read_text())["images"]
    assert [e["path"] for e in inputs] == ["../pair0.png", "../pair1.png", *(f"keyframes/{k}" for k in keyframes)]
    assert inputs[2]["absolute"] == str((tmp_path / "out" / "keyframes" / keyframes[0]).resolve())
