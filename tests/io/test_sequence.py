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


def test_the_fingerprint_never_holds_a_file_whole(files, tmp_path, monkeypatch):
    """Issue 48 row 12: a 3 GB file the walk skips by its header cost 3.2 GB to fingerprint. The
    files are hashed a chunk at a time: the same digest as their whole bytes'."""
    import hashlib
    from pathlib import Path

    from stereoseed.io import sequence

    big = tmp_path / "big.png"
    big.write_bytes(Path(files[0]).read_bytes() + bytes(3 * sequence._FINGERPRINT_CHUNK + 5))
    entries = [big] + list(files[1:])
    want = hashlib.sha256(b"".join(Path(f).read_bytes() for f in entries)).digest()  # no transform: no key
    read = []
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: read.append(self) or real(self))
    assert ImageSequence(entries).fingerprint() == want and read == []


def test_an_unreadable_image_of_the_walk_reads_as_empty_and_says_why(files, tmp_path):
    """From the first covered image on, a text file named .png and a truncated PNG do not raise:
    each reads as a black image of its header's size (for the text: the size expected, if any)
    holding no pixels, and says the reader's reason; an image before the first covered one
    still raises."""
    text = tmp_path / "text.png"
    text.write_text("not an image\n")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(files[2].read_bytes()[:200])
    seq = ImageSequence([files[0], files[1], text, truncated, files[4]])
    seq.skip_unreadable(first=2)
    assert seq.unreadable(0) is None and seq.unreadable(4) is None
    assert seq.unreadable(2).startswith(f"{text}: not a readable image") and "not an image format" in seq.unreadable(2)
    assert seq.unreadable(3).startswith(f"{truncated}: not a readable image") and "truncated PNG" in seq.unreadable(3)
    assert seq[2].shape == (0, 0, 3)  # no header, no size expected
    blank = seq[3]
    assert blank.shape == (60, 80, 3) and not blank.any()
    assert blank.strides[:2] == (0, 0)  # the header's size, no memory
    reads = seq.reads
    seq[3], seq[3]
    assert seq.reads == reads  # decoded once: the answer stays for the run
    part = seq[1:]  # a slice keeps what is covered
    assert part.unreadable(1) == seq.unreadable(2) and part.unreadable(0) is None
    seq.withhold_other_sizes((80, 60), first=2)
    assert seq[2].shape == (60, 80, 3)  # the size the images are expected to have
    later = ImageSequence([files[0], text])
    later.skip_unreadable(first=2)
    with pytest.raises(StereoseedError, match="text.png: not a readable image"):
        later[1]  # the pair's images are not covered: they fail the run before any work
