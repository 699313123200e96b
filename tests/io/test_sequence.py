"""ImageSequence reads images when asked and keeps a few."""
import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.io.files import write_image
from stereoseed.io.sequence import ImageSequence


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


def test_the_fingerprint_reads_the_files_without_decoding_them(files, tmp_path):
    seq = ImageSequence(files)
    key = seq.fingerprint()
    assert seq.reads == 0 and ImageSequence(files).fingerprint() == key
    assert ImageSequence(files, transform_key=b"a lens").fingerprint() != key  # what the transform depends on
    assert seq[1:].fingerprint() != key
    changed = tmp_path / "changed.png"
    write_image(changed, np.zeros((8, 8, 3), np.uint8))
    assert ImageSequence([files[0], changed] + list(files[2:])).fingerprint() != key
