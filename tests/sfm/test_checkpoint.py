"""Checkpoints of a long run: the descriptors of old views named, not copied, and a resumed run
that reads its images from disk ends where the uninterrupted one does."""
import pickle

import numpy as np
import pytest

from stereoseed import pipeline
from stereoseed.sfm.checkpoint import CheckpointWriter, spill_folder
from stereoseed.errors import StereoseedError
from stereoseed.sfm.reconstruction import Reconstruction, View
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
    whole, _ = pipeline.reconstruct(images, names, P_pair, cfg, checkpoint=tmp_path / "whole.pkl")

    checkpoint = tmp_path / "run.pkl"
    insert = pipeline.insert_view

    def interrupted(recon, k, cfg):
        if k == 11:
            raise KeyboardInterrupt
        return insert(recon, k, cfg)

    monkeypatch.setattr(pipeline, "insert_view", interrupted)
    images, names, P_pair = pipeline.load_sequence(images_txt, calib)
    with pytest.raises(KeyboardInterrupt):
        pipeline.reconstruct(images, names, P_pair, cfg, checkpoint=checkpoint)
    # views 3-5 left the working set (the first 3 and the last 5 stay): their descriptors are
    # in files beside the checkpoint, which names them
    with open(checkpoint, "rb") as fh:
        views = pickle.load(fh)["views"]
    spilled = [i for i, v in enumerate(views) if v[1] is not None and isinstance(v[1][1], tuple)]
    assert spilled == [3, 4, 5]
    assert all((spill_folder(checkpoint) / views[i][1][1][1]).is_file() for i in spilled)

    monkeypatch.setattr(pipeline, "insert_view", insert)
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
    from stereoseed.output.results import ResultSet

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
    assert spill_folder(tmp_path / "sub" / ".." / "ck.pkl") == tmp_path / "ck.pkl.spill"


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


def _small_reconstruction() -> Reconstruction:
    recon = Reconstruction([View("a"), View("b")])
    recon.add_points(np.arange(12.0).reshape(4, 3), np.zeros((4, 3), np.uint8))
    return recon


def test_a_background_checkpoint_is_the_state_when_saved(tmp_path):
    """The run goes on changing the model while the thread writes: the file holds the snapshot."""
    recon = _small_reconstruction()
    path = tmp_path / "run.pkl"
    with CheckpointWriter(path, "key") as writer:
        writer.save(recon, [{"image": "a"}])
        recon.points[:] = -1.0
        recon.add_points(np.ones((2, 3)), np.zeros((2, 3), np.uint8))
    payload = pickle.loads(path.read_bytes())
    assert payload["key"] == "key" and payload["per_image"] == [{"image": "a"}]
    np.testing.assert_array_equal(payload["points"], np.arange(12.0).reshape(4, 3))


def test_a_failed_background_checkpoint_is_reported(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(StereoseedError, match="cannot write"):
        with CheckpointWriter(tmp_path / "a_file" / "run.pkl", "key") as writer:
            writer.save(_small_reconstruction(), [])


def test_a_failed_background_checkpoint_does_not_hide_the_runs_own_error(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(KeyError, match="the run's"):
        with CheckpointWriter(tmp_path / "a_file" / "run.pkl", "key") as writer:
            writer.save(_small_reconstruction(), [])
            raise KeyError("the run's")
