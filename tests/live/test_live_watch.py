"""The watched folder: a photo is taken once complete, each once; a file still being written, one
deleted before or after it was taken, one that does not decode, a video: each said in a line."""
from __future__ import annotations

import os

import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.io.files import write_image
from stereoseed.live.config import LiveConfig
from stereoseed.live.watch import FolderWatch

CFG = LiveConfig(stable_s=0.5, unreadable_after_s=2.0)


@pytest.fixture
def png(tmp_path):
    """A small PNG's bytes."""
    rng = np.random.default_rng(0)
    path = write_image(tmp_path / "x.png", rng.integers(0, 255, (40, 50, 3), dtype=np.uint8))
    data = path.read_bytes()
    path.unlink()
    return data


def test_a_photo_is_taken_once_its_size_has_settled_and_it_decodes(tmp_path, png):
    watch = FolderWatch(tmp_path, CFG)
    half = tmp_path / "a.png"
    half.write_bytes(png[: len(png) // 2])
    assert not watch.look(0.0).arrivals
    half.write_bytes(png[: 3 * len(png) // 4])  # still being written
    os.utime(half, ns=(1, 10**9))
    look = watch.look(0.3)
    assert not look.arrivals and look.notes == ["a.png: still being written; waiting for it"]
    half.write_bytes(png)
    os.utime(half, ns=(1, 2 * 10**9))
    assert not watch.look(0.6).arrivals  # complete, but not settled yet
    look = watch.look(1.2)
    assert [a.name for a in look.arrivals] == ["a.png"] and look.arrivals[0].data == png
    assert look.arrivals[0].decodes and look.arrivals[0].settled_at == 0.6
    assert not watch.look(2.0).arrivals  # taken once


def test_photos_settled_together_come_in_the_order_they_were_written(tmp_path, png):
    watch = FolderWatch(tmp_path, CFG)
    for i, name in enumerate(("d.png", "b.png", "a.png", "c.jpg.part")):
        (tmp_path / name).write_bytes(png)
        os.utime(tmp_path / name, ns=(1, (10 + min(i, 1)) * 10**9))  # b.png and a.png written in the same second
    first = watch.look(0.0)
    look = watch.look(1.0)
    assert [a.name for a in look.arrivals] == ["d.png", "a.png", "b.png"]
    assert first.notes == ["c.jpg.part: not an image by its extension; not taken"] and not look.notes  # said once


def test_a_file_deleted_before_or_after_it_was_taken_is_said(tmp_path, png):
    watch = FolderWatch(tmp_path, CFG)
    (tmp_path / "gone.png").write_bytes(png[:100])
    (tmp_path / "kept.png").write_bytes(png)
    watch.look(0.0)
    (tmp_path / "gone.png").unlink()
    look = watch.look(1.0)
    assert [a.name for a in look.arrivals] == ["kept.png"]
    assert look.notes == ["gone.png: deleted before it was complete; not taken"]
    (tmp_path / "kept.png").unlink()
    look = watch.look(1.5)
    assert look.notes == [f"kept.png: deleted from {tmp_path} after it was taken; the run keeps its copy"]
    (tmp_path / "kept.png").write_bytes(png)  # a new photo under a name taken already
    look = watch.look(2.0)
    assert not look.arrivals and "taken already" in look.notes[0]


def test_a_file_that_does_not_decode_is_waited_for_then_taken_as_unreadable(tmp_path, png):
    watch = FolderWatch(tmp_path, CFG)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 200)
    watch.look(0.0)
    look = watch.look(1.0)
    assert not look.arrivals and "not decodable yet" in look.notes[0]
    look = watch.look(2.5)  # past unreadable_after_s: taken, the run skips it with its reason
    assert [(a.name, a.decodes) for a in look.arrivals] == [("bad.png", False)]


def test_a_video_or_a_folder_that_is_not_there(tmp_path):
    (tmp_path / "walk.mp4").write_bytes(b"0" * 10)
    assert FolderWatch(tmp_path, CFG).look(0.0).notes == ["walk.mp4: a video: give it with --video; not taken"]
    with pytest.raises(StereoseedError, match="not a folder"):
        FolderWatch(tmp_path / "nowhere", CFG)


def test_a_watched_folder_that_goes_away_is_said_once(tmp_path, png):
    folder = tmp_path / "w"
    folder.mkdir()
    watch = FolderWatch(folder, CFG)
    folder.rmdir()
    notes = watch.look(0.0).notes + watch.look(0.2).notes
    assert len(notes) == 1 and "cannot be listed" in notes[0]
    folder.mkdir()
    (folder / "a.png").write_bytes(png)
    assert watch.look(0.4).notes == [f"{folder}: can be listed again"]
    assert [a.name for a in watch.look(1.0).arrivals] == ["a.png"]


def test_the_settings_are_checked_when_built():
    with pytest.raises(ValueError, match="LiveConfig.stable_s"):
        LiveConfig(stable_s=0)

