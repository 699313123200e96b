"""Checkpoints of a long run: the descriptors of old views named, not copied, and a resumed run
that reads its images from disk ends where the uninterrupted one does; a checkpoint that is not
the run's own (planted, altered, another user's) is refused, never executed."""
import json
import logging
import os

import numpy as np
import pytest

from stereoseed import pipeline
from stereoseed.features.harris import Features
from stereoseed.scene import checkpoint as ck
from stereoseed.scene.view_store import release_pixels
from stereoseed.scene.checkpoint import CheckpointWriter, load_checkpoint, save_checkpoint, spill_folder
from stereoseed.errors import StereoseedError
from stereoseed.scene.camera_life import Flag
from stereoseed.scene.reconstruction import Reconstruction, View
from stereoseed.config import Config
from scene_helpers import scene_on_disk


@pytest.fixture(scope="module")
def ring_on_disk(small_box_scene, tmp_path_factory):
    """A 14-image box ring of 320x240 images written as PNGs with its true pair: (images.txt,
    calib.json). Small images: the spilling and resuming do not depend on the size."""
    paths, calib = scene_on_disk(small_box_scene, tmp_path_factory.mktemp("ring"))
    return str(paths["images_txt"]), str(calib)


def test_an_interrupted_run_resumes_from_spilled_descriptors_to_the_same_cameras(ring_on_disk, tmp_path,
                                                                                  monkeypatch):
    images_txt, calib = ring_on_disk
    cfg = Config()
    images, names, P_pair = pipeline.load_sequence(images_txt, calib)
    whole, _ = pipeline.reconstruct(images, names, P_pair, cfg, checkpoint=tmp_path / "whole.npz")

    checkpoint = tmp_path / "run.npz"
    from stereoseed.sfm import steps  # the insertion reconstruct and the live run share
    insert = steps.insert_view

    def interrupted(recon, k, cfg, source):
        if k == 11:
            raise KeyboardInterrupt
        return insert(recon, k, cfg, source)

    monkeypatch.setattr(steps, "insert_view", interrupted)
    images, names, P_pair = pipeline.load_sequence(images_txt, calib)
    with pytest.raises(KeyboardInterrupt):
        pipeline.reconstruct(images, names, P_pair, cfg, checkpoint=checkpoint)
    # views 3-5 left the working set (the first 3 and the last 5 stay): their descriptors are
    # in files beside the checkpoint, which names them
    views = _meta_of(checkpoint)["views"]
    spilled = [i for i, v in enumerate(views) if v["desc_file"] is not None]
    assert spilled == [3, 4, 5]
    assert all((spill_folder(checkpoint) / views[i]["desc_file"]).is_file() for i in spilled)

    monkeypatch.setattr(steps, "insert_view", insert)
    images, names, P_pair = pipeline.load_sequence(images_txt, calib)
    resumed, report = pipeline.reconstruct(images, names, P_pair, cfg, checkpoint=checkpoint, resume=True)
    assert report["resumed_images"] == names[:11]
    assert resumed.registered_views == whole.registered_views
    for a, b in zip(resumed.views, whole.views):
        np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-9 * np.abs(b.P).max())
    # the resumed views read their images when needed instead of holding them
    assert all(v._image is None for v in resumed.views)


def test_a_resume_with_a_mistyped_input_keeps_its_checkpoint(ring_on_disk, tmp_path):
    from stereoseed.errors import StereoseedError
    from stereoseed.output.result_set import ResultSet

    images_txt, _ = ring_on_disk
    out = tmp_path / "out"
    staging = ResultSet(out).open()
    (staging / pipeline.CHECKPOINT).write_bytes(b"the work of an interrupted run")
    with pytest.raises(StereoseedError):
        pipeline.reconstruct_to_folder(images_txt, str(tmp_path / "calib_typo.json"), out, resume=True)
    assert (staging / pipeline.CHECKPOINT).read_bytes() == b"the work of an interrupted run"


def test_the_spill_folder_is_named_as_memory_maps_name_their_files(tmp_path):
    # a memory map's file name is normalised (os.path.abspath): "sub/.." must not hide the match
    (tmp_path / "sub").mkdir()
    assert spill_folder(tmp_path / "sub" / ".." / "ck.npz") == tmp_path / "ck.npz.spill"


def test_a_long_run_may_keep_a_memory_map_per_view_open():
    resource = pytest.importorskip("resource")
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2048:
        pytest.skip(f"the hard open-file limit is {hard}")
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard))  # a common default
        pipeline._allow_open_files(2048)
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] == 2048
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def _meta_of(path) -> dict:
    with np.load(path, allow_pickle=False) as npz:
        return json.loads(npz["meta"].tobytes().decode("utf-8"))


def _small_reconstruction() -> Reconstruction:
    recon = Reconstruction([View("a"), View("b")])
    recon.add_points(np.arange(12.0).reshape(4, 3), np.zeros((4, 3), np.uint8))
    return recon


def test_a_background_checkpoint_is_the_state_when_saved(tmp_path):
    """The run goes on changing the model while the thread writes: the file holds the snapshot."""
    recon = _small_reconstruction()
    path = tmp_path / "run.npz"
    with CheckpointWriter(path, "key") as writer:
        recon.record(0, {"image": "a"})
        writer.save(recon)
        recon.points[:] = -1.0
        recon.record(1, {"image": "b"})
        recon.add_points(np.ones((2, 3)), np.zeros((2, 3), np.uint8))
    meta = _meta_of(path)
    assert meta["key"] == "key" and [v["history"] for v in meta["views"]] == [
        [{"event": "Inserted", "report": {"image": "a"}}], []]
    with np.load(path, allow_pickle=False) as npz:
        np.testing.assert_array_equal(npz["points"], np.arange(12.0).reshape(4, 3))


def test_a_failed_background_checkpoint_is_reported(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(StereoseedError, match="cannot write"):
        with CheckpointWriter(tmp_path / "a_file" / "run.npz", "key") as writer:
            writer.save(_small_reconstruction())


def test_a_failed_background_checkpoint_does_not_hide_the_runs_own_error(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(KeyError, match="the run's"):
        with CheckpointWriter(tmp_path / "a_file" / "run.npz", "key") as writer:
            writer.save(_small_reconstruction())
            raise KeyError("the run's")


# ------------------------------------------------------------------ a checkpoint from outside
KEY = "0123456789abcdef" * 4  # an inputs key (a hex digest)


class _Planted:
    """What a planted pickle would hold: unpickling it creates the file ``marker``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _planted_pickle(marker) -> bytes:
    import pickle

    return pickle.dumps({"version": 2, "views": [_Planted(marker)]})


def test_the_planted_pickle_would_run_if_unpickled(tmp_path):
    """The payload the tests below plant does run its code when unpickled: the marker not
    appearing there is the checkpoint's doing."""
    import pickle

    marker = tmp_path / "ran"
    pickle.loads(_planted_pickle(marker))
    assert marker.exists()


class _Saved:
    def __init__(self, path, images, names, recon, per_image):
        self.path, self.images, self.names, self.recon, self.per_image = path, images, names, recon, per_image


@pytest.fixture
def saved(tmp_path) -> _Saved:
    """A checkpoint of three views (the first two registered, the second turned by 180 degrees
    with the focal-only model, the first's descriptors spilled beside the checkpoint), five
    points seen by both registered views, and the reports."""
    rng = np.random.default_rng(1)
    path = tmp_path / "staging" / "ck.npz"
    names = ["a.png", "b.png", "c.png"]
    images = [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in names]
    K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
    views = []
    for i, name in enumerate(names):
        n = 6 + i
        features = Features(rng.uniform(0, 30, (n, 2)), rng.standard_normal((n, 9)).astype(np.float32),
                            rng.random(n) > 0.2, rng.random(n), (24, 32))
        P = K @ np.hstack([np.eye(3), [[0.1 * i], [0.0], [0.0]]]) if i < 2 else None
        views.append(View(name, features, P=P, point_of_feature=np.full(n, -1, np.int64), image=images[i],
                          rotated_180=i == 1, camera_model="focal" if i == 1 else None, zoomed=i == 1))
    recon = Reconstruction(views)
    recon.calibrate(0, views[0].P)
    recon.register(1, views[1].camera, "motion prior", views[1].features, images[1], True, "focal", True,
                   Flag.parse("ambiguous: repeated structure (as a run would say)"))
    ids = recon.add_points(rng.standard_normal((5, 3)) + [0.0, 0.0, 5.0], rng.integers(0, 256, (5, 3)))
    recon.add_observations(0, np.arange(5), ids)
    recon.add_observations(1, np.arange(1, 6), ids)
    recon.add_observations(1, [0], ids[:1], link=False)
    spill_folder(path).mkdir(parents=True)
    release_pixels(recon.views[0], spill_folder(path))
    per_image = [{"image": "a.png", "status": "calibrated"},
                 {"image": "b.png", "status": "calibrated pair", "new_points": np.int64(5), "rms": 0.25}]
    for i, report in enumerate(per_image):
        recon.record(i, report)
    save_checkpoint(path, recon, KEY)
    return _Saved(path, images, names, recon, per_image)


def _load(saved: _Saved, key: str = KEY):
    return load_checkpoint(saved.path, saved.images, saved.names, key)


def test_a_checkpoint_gives_back_the_model_and_reports_with_spilled_descriptors_named(saved):
    recon, per_image = _load(saved)
    assert per_image == [{"image": "a.png", "status": "calibrated"},
                         {"image": "b.png", "status": "calibrated pair", "new_points": 5, "rms": 0.25}]
    for name in ("points", "colors", "alive", "obs_view", "obs_feature", "obs_point", "obs_linked"):
        np.testing.assert_array_equal(getattr(recon, name), getattr(saved.recon, name))
    for a, b in zip(recon.views, saved.recon.views):
        assert (a.name, a.status, a.rotated_180, a.camera_model, a.zoomed, a.placement_flag, a.found_by) == \
            (b.name, b.status, b.rotated_180, b.camera_model, b.zoomed, b.placement_flag, b.found_by)
        assert a.history == b.history  # a resume replays the same history
        assert (a.P is None and b.P is None) or np.array_equal(a.P, b.P)
        for field in ("points", "desc", "valid", "response"):
            np.testing.assert_array_equal(getattr(a.features, field), getattr(b.features, field))
        assert a.features.image_shape == b.features.image_shape
        np.testing.assert_array_equal(a.point_of_feature, b.point_of_feature)
    # the spilled descriptors are memory-mapped from their file, not copied into the checkpoint
    assert recon.views[0].features.desc.filename == saved.recon.views[0].features.desc.filename
    with np.load(saved.path, allow_pickle=False) as npz:
        assert "view0.desc" not in npz.files and "view1.desc" in npz.files
    np.testing.assert_array_equal(recon.views[1].image, saved.images[1][::-1, ::-1])  # turned as the run turned it
    assert os.stat(saved.path).st_mode & 0o077 == 0  # the user's alone


def _refused(saved: _Saved, caplog, why: str, key: str = KEY) -> None:
    with caplog.at_level(logging.WARNING, logger="stereoseed.scene.checkpoint"):
        assert _load(saved, key) is None
    assert "starting again" in caplog.text and why in caplog.text, caplog.text


def _rewrite(saved: _Saved, change, key: str | None = KEY) -> None:
    """The checkpoint with ``change(arrays, meta)`` applied, signed again with ``key`` (as
    someone who can read the inputs could), or, with ``key`` None, with its old signature."""
    with np.load(saved.path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    meta = json.loads(arrays.pop("meta").tobytes().decode("utf-8"))
    change(arrays, meta)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), np.uint8)
    if key is not None:
        arrays.pop("mac")
        ck._write(saved.path, arrays, key)
    else:
        with open(saved.path, "wb") as fh:  # keeps the file's mode
            np.savez(fh, **arrays)


def test_a_planted_pickle_at_the_checkpoint_is_never_run(saved, tmp_path, caplog):
    marker = tmp_path / "ran"
    saved.path.write_bytes(_planted_pickle(marker))
    _refused(saved, caplog, "pickled")
    assert not marker.exists()


def test_a_planted_object_array_is_never_unpickled(saved, tmp_path, caplog):
    marker = tmp_path / "ran"
    planted = np.empty(1, object)
    planted[0] = _Planted(marker)

    with np.load(saved.path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["points"] = planted
    with open(saved.path, "wb") as fh:
        np.savez(fh, allow_pickle=True, **arrays)
    _refused(saved, caplog, "holds objects")
    assert not marker.exists()


def _set(name, value):
    def change(arrays, meta):
        arrays[name] = value(arrays[name])
    return change


def _flag(view, name, value):
    def change(arrays, meta):
        meta["views"][view][name] = value
    return change


def _with_nan(a):
    a = a.astype(np.float64)
    a[0] = np.nan
    return a


def _out_of_range(a, value=999):
    a = a.copy()
    a[0] = value
    return a


@pytest.mark.parametrize("change, key, why", [
    (_set("points", lambda a: a + 1e-9), None, "signature"),  # altered, the old signature kept
    (_set("mac", lambda a: a ^ 1), None, "signature"),
    (_set("obs_point", _with_nan), KEY, "obs_point is float64"),
    (_set("obs_feature", _out_of_range), KEY, "obs_feature holds indices out of range"),
    (_set("obs_view", lambda a: _out_of_range(a, -1)), KEY, "obs_view holds indices out of range"),
    (_set("view1.point_of_feature", _out_of_range), KEY, "view1.point_of_feature holds indices out of range"),
    (_set("points", lambda a: a[:, :2].copy()), KEY, "points is float64 (5, 2)"),
    (_set("view1.desc", lambda a: a[:-1].copy()), KEY, "view1.desc is float32"),
    (_set("view0.P", lambda a: a.astype(np.float32)), KEY, "view0.P is float32"),
    (lambda arrays, meta: arrays.pop("view0.P"), KEY, "view0.P is missing"),
    (lambda arrays, meta: arrays.update(extra=np.zeros(1)), KEY, "unexpected arrays (extra)"),
    (_flag(0, "desc_file", "../x.npy"), KEY, "not a file name"),
    (_flag(0, "desc_file", "/etc/passwd"), KEY, "not a file name"),
    (_flag(0, "desc_file", "desc_gone.npy"), KEY, "cannot be read"),
    (_flag(0, "name", "z.png"), KEY, "description of 'a.png' is malformed"),
    (_flag(1, "zoomed", "yes"), KEY, "description of 'b.png' is malformed"),
    (_flag(1, "history", 3), KEY, "description of 'b.png' is malformed"),
    (_flag(1, "history", [{"event": "Registered", "found_by": "x", "code": "os.system"}]), KEY, "malformed Registered"),
    (lambda arrays, meta: meta.update(version=3), KEY, "another version"),
    (_flag(1, "history", []), KEY, "reports are not of these images"),
    (lambda arrays, meta: meta.update(insertion_undo={"view": 1, "views": meta["views"]}), KEY,
     "before the last insertion is malformed"),
    (_flag(0, "features_as_now", True), KEY, "description of 'a.png' is malformed"),
])
def test_an_altered_or_malformed_checkpoint_is_refused(saved, caplog, change, key, why):
    # the traversal's target exists and holds descriptors: only its name refuses it
    np.save(saved.path.parent / "x.npy", np.asarray(saved.recon.views[0].features.desc))
    _rewrite(saved, change, key)
    _refused(saved, caplog, why)


def test_a_checkpoint_of_other_inputs_is_refused(saved, caplog):
    _refused(saved, caplog, "signature", key="another inputs key")


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="no file owners")
@pytest.mark.parametrize("what", ["file", "folder", "spill folder", "spilled file"])
def test_a_checkpoint_others_may_write_is_refused(saved, caplog, what):
    target = {"file": saved.path, "folder": saved.path.parent, "spill folder": spill_folder(saved.path),
              "spilled file": saved.recon.views[0].features.desc.filename}[what]
    os.chmod(target, os.stat(target).st_mode | 0o020)  # group-writable
    _refused(saved, caplog, "may be written by group or others")


@pytest.mark.skipif(not hasattr(os, "getuid") or os.getuid() != 0, reason="giving a file away needs root")
def test_another_users_checkpoint_is_refused(saved, caplog):
    os.chown(saved.path, 4321, -1)
    _refused(saved, caplog, "belongs to another user")


@pytest.mark.skipif(not hasattr(os, "O_NOFOLLOW"), reason="no O_NOFOLLOW")
def test_a_link_in_place_of_the_checkpoint_is_refused(saved, caplog):
    real = saved.path.with_name("elsewhere.npz")
    saved.path.rename(real)
    saved.path.symlink_to(real)
    _refused(saved, caplog, "unusable checkpoint")


def test_a_planted_pickle_beside_the_output_is_never_run(ring_on_disk, tmp_path, caplog):
    """At the checkpoint's name and at the name pickled checkpoints had: neither runs, and the
    run starts again."""
    from stereoseed.output.result_set import ResultSet

    images_txt, calib = ring_on_disk
    out = tmp_path / "out"
    staging = ResultSet(out).open()
    marker = tmp_path / "ran"
    (staging / ".checkpoint.pkl").write_bytes(_planted_pickle(marker))
    (staging / pipeline.CHECKPOINT).write_bytes(_planted_pickle(marker))
    with caplog.at_level(logging.WARNING, logger="stereoseed.scene.checkpoint"):
        report = pipeline.reconstruct_to_folder(images_txt, calib, out, resume=True)
    assert not marker.exists()
    assert "resumed_images" not in report and report["registered"] == report["images"]
    assert "starting again" in caplog.text


def test_a_resumed_run_keeps_the_flags_its_registrations_raised(plain_box_scene, tmp_path):
    from stereoseed.config import Config
    from stereoseed.pipeline import reconstruct

    s = plain_box_scene.prefix(6)
    ck = tmp_path / "ck.npz"
    _, first = reconstruct(s.images, s.names, s.P[:2], Config(), checkpoint=ck)
    recon, resumed = reconstruct(s.images, s.names, s.P[:2], Config(), checkpoint=ck, resume=True)
    flagged = first["final"]["trust"]["flagged"]
    assert any(r.startswith("ambiguous") for r in flagged.values())  # the squares: chosen on a margin
    assert resumed["final"]["trust"]["flagged"] == flagged
    # what placed each camera, which the judgement in hindsight reads, as the reports said
    placed_by = [r.get("registered_by") for r in first["per_image"][2:]]
    assert [v.found_by for v in recon.views[2:]] == placed_by and "motion prior" in placed_by


def test_a_fifo_planted_as_the_checkpoint_is_refused_without_waiting(saved, caplog):
    # opened for reading, a FIFO blocks until someone writes to it: the resume would hang
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this system")
    saved.path.unlink()
    os.mkfifo(saved.path, 0o600)
    with caplog.at_level(logging.WARNING):
        assert _load(saved) is None
    assert "not a file" in caplog.text


def test_the_header_is_read_under_the_checks_of_the_whole_checkpoint(saved, caplog):
    """A live run reads which inputs its checkpoint was signed for before it can check the
    signature: what it says, from the very file load_checkpoint would read, never from a link,
    a FIFO or a file others may write."""
    from stereoseed.scene.checkpoint import checkpoint_header

    assert checkpoint_header(saved.path) == (3, KEY)
    assert checkpoint_header(saved.path.with_name("none.npz")) is None
    os.chmod(saved.path, os.stat(saved.path).st_mode | 0o020)
    with caplog.at_level(logging.WARNING):
        assert checkpoint_header(saved.path) is None
    assert "may be written by group or others" in caplog.text
    saved.path.unlink()
    if hasattr(os, "mkfifo"):
        os.mkfifo(saved.path, 0o600)
        assert checkpoint_header(saved.path) is None  # at once: a FIFO is not waited on
