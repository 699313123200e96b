"""ImageSequence reads images when asked and keeps a few; views load, release and restore what
a long run does not need to hold."""
import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.features.harris import extract_features
from stereoseed.io.files import write_image
from stereoseed.sfm.reconstruction import View
from stereoseed.io.sequence import ImageSequence
from geometry_helpers import band_noise


@pytest.fixture
def files(tmp_path):
    paths = []
    for i in range(5):
        image = (np.dstack([band_noise((60, 80), seed=i)] * 3) * 255).astype(np.uint8)
        paths.append(write_image(tmp_path / f"{i}.png", image))
    return paths


def test_images_are_read_when_asked_and_the_last_few_kept(files):
    seq = ImageSequence(files, transform=lambda i, im: im[:, ::-1].copy(), capacity=2)
    assert len(seq) == 5 and seq.reads == 0
    first = seq[0]
    assert seq[0] is first and seq.reads == 1  # cached
    seq[1], seq[2]
    assert seq.reads == 3
    again = seq[0]  # evicted by 1 and 2: read again, same pixels
    assert again is not first and np.array_equal(again, first) and seq.reads == 4
    assert not again.flags.writeable  # shared: nobody may change it in place
    assert seq[-1].shape == (60, 80, 3)
    sub = seq[1:4]
    assert len(sub) == 3 and np.array_equal(sub[0], seq[1])  # the transform follows the slice
    with pytest.raises(IndexError):
        seq[5]


def test_an_unreadable_image_is_reported_when_read(files, tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    seq = ImageSequence([files[0], bad])
    seq[0]
    with pytest.raises(StereoseedError, match="bad.png"):
        seq[1]


def test_a_view_releases_its_grey_image_and_restores_the_same_one(files):
    seq = ImageSequence(files, capacity=1)
    view = View("0.png", load=lambda: seq[0])
    view.features = extract_features(view.image)
    gray = view.features.gray.copy()
    assert view.image_size == (80, 60)
    state = view._state()
    view.release_pixels()
    assert view.features.gray is None
    seq[1]  # evicts image 0
    assert np.array_equal(view.restore_gray().gray, gray)
    view.release_pixels()
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
    view.release_pixels(spill_to=tmp_path)
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
    monkeypatch.setattr(pipeline, "_release_pixels", lambda recon, cfg, folder: None)
    kept, _ = pipeline.reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert not any(isinstance(v.features.desc, np.memmap) for v in kept.views)
    for a, b in zip(spilled.views, kept.views):
        assert (a.P is None) == (b.P is None)
        if a.P is not None:
            np.testing.assert_array_equal(a.P, b.P)


def test_the_fingerprint_reads_the_files_without_decoding_them(files, tmp_path):
    seq = ImageSequence(files)
    key = seq.fingerprint()
    assert seq.reads == 0 and ImageSequence(files).fingerprint() == key
    assert ImageSequence(files, transform_key=b"a lens").fingerprint() != key  # what the transform depends on
    assert seq[1:].fingerprint() != key
    changed = tmp_path / "changed.png"
    write_image(changed, np.zeros((8, 8, 3), np.uint8))
    assert ImageSequence([files[0], changed] + list(files[2:])).fingerprint() != key
