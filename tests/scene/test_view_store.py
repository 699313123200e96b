"""The view store: a view's grey image let go and computed again, its descriptors spilled to a
file and read back, and a long run that spills finding the cameras of one that keeps everything."""
import numpy as np

from stereoseed.features.harris import extract_features
from stereoseed.io.sequence import ImageSequence
from stereoseed.scene.reconstruction import View
from stereoseed.scene.view_store import release_pixels


def test_a_view_releases_its_grey_image_and_restores_the_same_one(files):
    seq = ImageSequence(files, capacity=1)
    view = View("0.png", load=lambda: seq[0])
    view.features = extract_features(view.image)
    gray = view.features.gray.copy()
    assert view.image_size == (80, 60)
    state = view._state()
    release_pixels(view)
    assert view.features.gray is None
    seq[1]  # evicts image 0
    assert np.array_equal(view.restore_gray().gray, gray)
    release_pixels(view)
    released = view._state()
    view._restore(state)  # a rollback to before the release keeps its grey image
    assert view.features.gray is not None
    view._restore(released)  # and one to after it can still restore it
    assert np.array_equal(view.restore_gray().gray, gray)
    # a view whose image was given in memory, not loadable, keeps it: keep_image holds it
    held = View("x", image=seq[0])
    held.keep_image(seq[0], rotated_180=False)
    assert held.image is not None


def test_descriptors_spill_to_a_file_and_read_back_the_same(files, tmp_path):
    seq = ImageSequence(files)
    view = View("0.png", load=lambda: seq[0])
    view.features = extract_features(view.image)
    desc = view.features.desc.copy()
    release_pixels(view, spill_to=tmp_path)
    assert isinstance(view.features.desc, np.memmap) and np.array_equal(view.features.desc, desc)
    assert list(tmp_path.glob("desc_*.npy"))


def test_a_long_run_spills_old_views_and_finds_the_same_cameras(monkeypatch, small_box_scene):
    """Views out of the working set give up their grey images and descriptors during the run;
    the cameras are those of a run that keeps everything in memory."""
    from stereoseed import pipeline
    from stereoseed.config import Config

    scene = small_box_scene.prefix(12)
    spilled, _ = pipeline.reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert sum(isinstance(v.features.desc, np.memmap) for v in spilled.views) >= 2
    from stereoseed.sfm import steps  # the insertion step reconstruct and the live run share

    monkeypatch.setattr(steps, "release_old_views", lambda recon, options, folder: None)
    kept, _ = pipeline.reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert not any(isinstance(v.features.desc, np.memmap) for v in kept.views)
    for a, b in zip(spilled.views, kept.views):
        assert (a.P is None) == (b.P is None)
        if a.P is not None:
            np.testing.assert_array_equal(a.P, b.P)
