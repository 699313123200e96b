"""Faults and hostile input around the result folder (issue "safe under faults and hostile
input"): runs that resume with other inputs, an --out that is a link, the current folder or
holds the inputs, two runs on one folder, the user's own files beside or in the way of ours, a
full disk, group-writable umasks, image names and lenses no result can hold, an image of the walk
that cannot be decoded (skipped with its reason, the run resumable). Each case is
refused with one line or handled; nothing the user wrote is removed or overwritten; every
subprocess is bounded by a timeout."""
from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from process_helpers import wait_until
from cli_helpers import cli_command, one_line_error, run
from scene_helpers import scene_on_disk
from stereoseed import pipeline
from stereoseed.cli import main
from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.output.result_set import MANIFEST, STAGING_MARKER, ResultSet
from stereoseed.sfm.registration.base import FailureKind

TIMEOUT_S = 120  # any subprocess: a hang fails the test instead of the suite
ONE_WORKER = Config().replace(dense={"workers": 1})  # the dense stage in this process: no pool to start


@pytest.fixture(scope="module")
def seq(tmp_path_factory, small_box_scene):
    """A 5-image ring of 320x240 images on disk: (write_scene's paths, calib.json)."""
    folder = tmp_path_factory.mktemp("faults_seq")
    return scene_on_disk(small_box_scene.prefix(5), folder, images=folder / "images")


def listing(seq, folder: Path, count: int) -> Path:
    """A list file of the sequence's first ``count`` images."""
    path = folder / f"first{count}.txt"
    path.write_text("".join(f"{p}\n" for p in seq[0]["images"][:count]))
    return path


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` (files with their bytes, folders as None)."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))}


def interrupted_run(monkeypatch, seq, out: Path, images=None, dense: bool = True) -> Path:
    """A run stopped (as by Ctrl-C) once every image is placed and dense.ply is staged, before
    the results are written: its staging folder."""
    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(pipeline, "save_outputs", stop)
        with pytest.raises(KeyboardInterrupt):
            pipeline.reconstruct_to_folder(str(images or seq[0]["images_txt"]), str(seq[1]), out, ONE_WORKER,
                                           dense=dense)
    staging = out.parent / f".{out.name}.partial"
    assert (staging / pipeline.CHECKPOINT).is_file()
    return staging


def listed(out: Path) -> list[str]:
    return sorted(json.loads((out / MANIFEST).read_text())["files"])


def on_disk(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != MANIFEST)


# --- 1. a resume with other inputs or settings keeps nothing stale ------------------------------
def test_a_resume_with_other_inputs_starts_again_from_an_empty_staging_folder(seq, tmp_path, monkeypatch):
    out = tmp_path / "o"
    staging = interrupted_run(monkeypatch, seq, out)
    assert (staging / "dense.ply").is_file()
    report = pipeline.reconstruct_to_folder(str(listing(seq, tmp_path, 4)), str(seq[1]), out, ONE_WORKER, resume=True)
    assert "resumed_images" not in report  # the checkpoint is of five images: not used
    assert len(json.loads((out / "cameras.json").read_text())["images"]) == 4
    assert not (out / "dense.ply").exists() and "dense.ply" not in listed(out)
    assert listed(out) == on_disk(out) and not staging.exists()


def test_a_resume_without_dense_keeps_the_checkpoint_but_not_the_dense_cloud(seq, tmp_path, monkeypatch):
    out = tmp_path / "o"
    interrupted_run(monkeypatch, seq, out)
    report = pipeline.reconstruct_to_folder(str(seq[0]["images_txt"]), str(seq[1]), out, ONE_WORKER, resume=True)
    assert len(report["resumed_images"]) == 5  # the same inputs and settings: every image from the checkpoint
    assert not (out / "dense.ply").exists() and listed(out) == on_disk(out)


def test_an_unusable_checkpoint_is_removed_with_its_spill_folder_before_starting_again(seq, tmp_path):
    out = tmp_path / "o"
    staging = ResultSet(out).open()
    (staging / pipeline.CHECKPOINT).write_bytes(b"not a checkpoint")
    spill = staging / (pipeline.CHECKPOINT + ".spill")
    spill.mkdir()
    (spill / "desc_stale.npy").write_bytes(b"stale")
    seen = []
    original = pipeline.initialise

    def initialise(*args, **kwargs):  # the moment the run starts again
        seen.append(sorted(p.name for p in staging.iterdir()))
        return original(*args, **kwargs)

    pipeline.initialise, saved = initialise, pipeline.initialise
    try:
        pipeline.reconstruct_to_folder(str(seq[0]["images_txt"]), str(seq[1]), out, resume=True)
    finally:
        pipeline.initialise = saved
    assert seen == [[STAGING_MARKER]]


# --- 2. --out a symbolic link ----------------------------------------------------------------------
def test_an_output_that_is_a_link_writes_its_target_and_stays_a_link(seq, tmp_path, capsys):
    target = tmp_path / "target"
    target.mkdir()
    link = tmp_path / "link"
    link.symlink_to(target)
    for _ in range(2):  # and again: every later run to it works
        code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", link, "--quiet")
        assert code == 0, err
        assert link.is_symlink() and os.readlink(link) == str(target)
        assert (target / "cameras.json").is_file() and listed(target) == on_disk(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "target"]


# --- 3. one run at a time on one folder ------------------------------------------------------------
_HOLD_LOCK = """
import sys
from stereoseed.output.result_set import ResultSet
with ResultSet(sys.argv[1]) as results:
    staging = results.open()
    (staging / "work.bin").write_bytes(b"a long run's work")
    print("locked", flush=True)
    sys.stdin.readline()
"""


def test_a_second_run_on_a_locked_folder_is_refused_at_once_and_touches_nothing(seq, tmp_path, capsys):
    out = tmp_path / "o"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(out)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = snapshot(tmp_path)
        for calib in (tmp_path / "typo.json", seq[1]):  # a mistyped run, then a valid one
            code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", calib, "--out", out, "--quiet")
            assert code == 2 and one_line_error(err), err
            assert f"another stereoseed run is writing {out} (pid {holder.pid})" in err
            assert snapshot(tmp_path) == before  # the first run's staging folder is intact
    finally:
        holder.communicate("\n", timeout=TIMEOUT_S)
    assert holder.returncode == 0 and not (tmp_path / ".o.lock").exists()
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--quiet")
    assert code == 0, err  # once it is let go, the folder is anyone's


def test_a_mistyped_run_during_a_real_run_leaves_it_to_finish(seq, tmp_path, capsys):
    out = tmp_path / "o"
    lock = tmp_path / ".o.lock"
    cmd = cli_command("reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--dense", "--quiet")
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: first.poll() is not None or (lock.exists() and str(first.pid) in lock.read_text()),
                          TIMEOUT_S), "the run never took its lock"
        assert first.poll() is None, "the first run ended before the second could start"
        code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", tmp_path / "typo.json",
                           "--out", out, "--quiet")
        assert code == 2 and f"(pid {first.pid})" in err
        _, first_err = first.communicate(timeout=TIMEOUT_S)
    finally:
        first.kill()
        first.wait(TIMEOUT_S)
    assert first.returncode == 0, first_err
    assert (out / "dense.ply").is_file() and listed(out) == on_disk(out)


def test_a_lock_file_that_is_a_link_or_not_ours_is_refused(seq, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    (tmp_path / ".o.lock").symlink_to(victim)
    (tmp_path / ".p.lock").write_text("my notes about p\n")
    for name in ("o", "p"):
        code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", tmp_path / name,
                           "--quiet")
        assert code == 2 and one_line_error(err) and ".lock" in err, err
    assert victim.read_text() == "mine" and (tmp_path / ".p.lock").read_text() == "my notes about p\n"
    assert not (tmp_path / "o").exists() and not (tmp_path / ".o.partial").exists()


# --- 4. the user's files beside or in the way of ours -----------------------------------------------
@pytest.mark.parametrize("kind", ["folder", "link"])
def test_a_partial_folder_stereoseed_did_not_make_is_refused_not_deleted(seq, tmp_path, capsys, kind):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    partial = tmp_path / ".o.partial"
    if kind == "folder":
        partial.mkdir()
        (partial / "thesis.tex").write_text("years of work")
    else:
        partial.symlink_to(mine)
    before = snapshot(tmp_path)
    for more in ([], ["--resume"]):
        code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", tmp_path / "o",
                           "--quiet", *more)
        assert code == 2 and one_line_error(err) and ".o.partial" in err, err
        assert snapshot(tmp_path) == before


def test_files_named_like_the_probe_and_an_old_result_are_left_alone(seq, tmp_path, capsys):
    for name in (".o.probe", ".o.old"):
        (tmp_path / name).write_text("mine")
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", tmp_path / "o", "--quiet")
    assert code == 0, err
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", tmp_path / "o", "--quiet")
    assert code == 0, err  # a rerun swaps a previous result set out
    assert all((tmp_path / n).read_text() == "mine" for n in (".o.probe", ".o.old"))
    assert sorted(p.name for p in tmp_path.iterdir()) == [".o.old", ".o.probe", "o"]


def test_an_empty_folder_the_user_made_in_the_results_is_not_deleted(seq, tmp_path, capsys):
    out = tmp_path / "o"
    assert run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--quiet")[0] == 0
    (out / "my notes").mkdir()
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--quiet")
    assert code == 2 and one_line_error(err) and "my notes/" in err
    assert (out / "my notes").is_dir()


def test_abandon_removes_only_a_staging_folder_stereoseed_made(tmp_path):
    (tmp_path / ".o.partial").mkdir()
    (tmp_path / ".o.partial" / "mine.txt").write_text("mine")
    ResultSet(tmp_path / "o").abandon()
    assert (tmp_path / ".o.partial" / "mine.txt").read_text() == "mine"


# --- 9. outputs refused before any work; a full disk keeps the resume point ---------------------------
def test_the_current_folder_or_a_folder_holding_the_inputs_is_refused_before_any_work(seq, tmp_path, capsys,
                                                                                     monkeypatch):
    def work_started(*args, **kwargs):
        raise AssertionError("the run started before refusing its --out")

    here = tmp_path / "a" / "here"
    here.mkdir(parents=True)
    monkeypatch.chdir(here)
    monkeypatch.setattr(pipeline, "reconstruct", work_started)
    # a previous result folder whose images are given as the inputs of the run that replaces it
    old = tmp_path / "old"
    (old / "keyframes").mkdir(parents=True)
    images = []
    for p in seq[0]["images"]:
        images.append(old / "keyframes" / p.name)
        images[-1].write_bytes(p.read_bytes())
    (old / MANIFEST).write_text(json.dumps({"files": [f"keyframes/{p.name}" for p in images]}))
    (tmp_path / "inputs.txt").write_text("".join(f"{p}\n" for p in images))
    for images_arg, out in ((seq[0]["images_txt"], "."), (seq[0]["images_txt"], tmp_path / "a"),
                            (tmp_path / "inputs.txt", old)):
        before = snapshot(tmp_path)
        code, _, err = run(capsys, "reconstruct", images_arg, "--calib", seq[1], "--out", out, "--quiet")
        assert code == 2 and one_line_error(err), (out, err)
        assert snapshot(tmp_path) == before


def test_a_full_disk_keeps_the_staging_folder_and_says_resume(seq, tmp_path, capsys, monkeypatch):
    def disk_full(*args, **kwargs):  # as io.atomic reports it: a one-line error raised from the OSError
        try:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "sparse.ply")
        except OSError as e:
            raise StereoseedError(f"sparse.ply: cannot write ({e.strerror})") from None

    out = tmp_path / "o"
    with monkeypatch.context() as m:
        m.setattr(pipeline, "save_outputs", disk_full)
        code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--quiet")
    assert code == 2 and one_line_error(err) and "--resume" in err and "disk is full" in err, err
    assert (tmp_path / ".o.partial" / pipeline.CHECKPOINT).is_file() and not out.exists()
    code, stdout, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", out, "--quiet",
                            "--resume")
    assert code == 0 and "resumed after 5 images" in stdout, err


# --- 10. umask, stale checkpoints ----------------------------------------------------------------
def test_under_a_group_writable_umask_an_interrupted_run_still_resumes(seq, tmp_path, monkeypatch):
    old = os.umask(0o002)
    try:
        out = tmp_path / "o"
        staging = interrupted_run(monkeypatch, seq, out, dense=False)
        spill = staging / (pipeline.CHECKPOINT + ".spill")
        assert stat.S_IMODE(staging.stat().st_mode) == 0o700 and stat.S_IMODE(spill.stat().st_mode) == 0o700
        report = pipeline.reconstruct_to_folder(str(seq[0]["images_txt"]), str(seq[1]), out, ONE_WORKER, resume=True)
        assert len(report["resumed_images"]) == 5
        assert stat.S_IMODE(out.stat().st_mode) == 0o775  # the result folder is the user's, as mkdir makes it
    finally:
        os.umask(old)


def test_commit_drops_every_stale_checkpoint(tmp_path):
    results = ResultSet(tmp_path / "o")
    staging = results.open()
    (staging / "cameras.json").write_text("{}")
    for name in (".checkpoint.pkl", ".checkpoint.npz", ".checkpoint.npz.tmp"):
        (staging / name).write_bytes(b"stale")
    (staging / ".checkpoint.npz.spill").mkdir()
    (staging / ".checkpoint.npz.spill" / "desc.npy").write_bytes(b"stale")
    out = results.commit(drop=(".checkpoint*",))
    assert on_disk(out) == ["cameras.json"] and listed(out) == ["cameras.json"]


def test_an_out_that_is_a_loop_of_links_or_a_mount_point_is_refused_before_any_work(seq, tmp_path, capsys,
                                                                                      monkeypatch):
    """Issue 48 rows 7 and 12: both failed after the whole run (the swap by renaming refused),
    a mount point leaving a staging folder every later run refused."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", loop)
    assert code == 2 and one_line_error(err) and f"{loop}: is a symbolic link that leads to no folder" in err
    volume = tmp_path / "volume"
    volume.mkdir()
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == volume or real(p))  # mounting needs privileges
    code, _, err = run(capsys, "reconstruct", seq[0]["images_txt"], "--calib", seq[1], "--out", volume)
    assert code == 2 and one_line_error(err) and f"{volume}: is a mount point" in err and "volume/results" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loop", "volume"]  # no staging folder, no lock left


@pytest.mark.parametrize("refused", ["moving the results away", "moving the new ones in"])
def test_a_swap_refused_at_commit_leaves_the_previous_results_and_a_staging_folder_the_next_run_takes(
        tmp_path, monkeypatch, refused):
    from stereoseed.output import result_set

    out = tmp_path / "o"
    first = ResultSet(out)
    (first.open() / "cameras.json").write_text("before")
    first.commit()
    second = ResultSet(out)
    (second.open() / "cameras.json").write_text("after")
    real = os.replace

    def busy(a, b):
        if Path(a) == (out if refused == "moving the results away" else second.staging):
            raise OSError(errno.EBUSY, "Device or resource busy")
        return real(a, b)

    with monkeypatch.context() as m:
        m.setattr(result_set, "_exchange", lambda a, b: False)
        m.setattr(result_set.os, "replace", busy)
        with pytest.raises(StereoseedError, match=r"the results could not be moved into place \(Device or resource "
                                                  r"busy\); they stay in .*\.o\.partial"):
            second.commit()
    assert (out / "cameras.json").read_text() == "before"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".o.partial", "o"]  # no empty .o.*.old left
    again = ResultSet(out)
    (again.open() / "cameras.json").write_text("again")  # the staging folder is still stereoseed's
    assert (again.commit() / "cameras.json").read_text() == "again"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
def test_a_fifo_planted_as_the_checkpoint_is_removed_not_read(tmp_path, caplog):
    """Issue 48 row 12: --resume opened a FIFO planted as the checkpoint and waited forever for a
    writer; the staging folder keeps only a regular file (or real folder) of the kept names."""
    results = ResultSet(tmp_path / "o")
    staging = results.open()
    os.mkfifo(staging / pipeline.CHECKPOINT)
    (staging / "spill").mkdir()
    (staging / "spill" / "kept.npy").write_bytes(b"x")
    assert results.open(keep=(pipeline.CHECKPOINT, "spill")) == staging
    assert sorted(p.name for p in staging.iterdir()) == [STAGING_MARKER, "spill"]
    assert "not a file or folder stereoseed writes; removed" in caplog.text


# --- 5. batch: one folder per sequence, inside the output root --------------------------------------
def _sequence_list(folder: Path, *outs: str) -> Path:
    path = folder / "sequences.txt"
    path.write_text("".join(f"images{n} calib.json {out}\n" for n, out in enumerate(outs)))
    return path


@pytest.mark.parametrize("outs, says", [
    (("x/../res", "res"), "lines 1 and 2: both write res"),
    (("res", "res/inner"), "lines 1 and 2: write one inside the other"),
    (("alias", "res"), "lines 1 and 2: both write res"),
])
def test_batch_refuses_two_lines_writing_one_folder_however_named(tmp_path, outs, says):
    from stereoseed.batch import read_sequence_list

    (tmp_path / "res").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path / "res")
    with pytest.raises(StereoseedError, match=says):
        read_sequence_list(_sequence_list(tmp_path, *outs))


def test_batch_keeps_every_result_under_the_output_root(tmp_path, capsys):
    from stereoseed.batch import read_sequence_list

    root = tmp_path / "lists"
    root.mkdir()
    for out in ("../../elsewhere", str(tmp_path / "abs"), "../lists2/x", "."):
        path = _sequence_list(root, "ok", out)
        with pytest.raises(StereoseedError, match="line 2: OUT .* lies outside the output root"):
            read_sequence_list(path)
        code = main(["batch", str(path), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and one_line_error(err) and "--allow-outside" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lists"] and sorted(p.name for p in root.iterdir()) == [
        "sequences.txt"]
    outside = read_sequence_list(_sequence_list(root, "ok", "../../elsewhere"), allow_outside=True)
    assert outside[1].out == str(tmp_path.parent / "elsewhere")


# --- 11. an image of the walk that cannot be decoded ----------------------------------------------
def corrupted(seq, folder: Path, kind: str, index: int = 3) -> Path:
    """A copy of the sequence whose image ``index`` is damaged (``kind``: a truncated PNG, or a
    text file named .png): its list file."""
    images = folder / "images"
    images.mkdir(parents=True)
    paths = [images / Path(p).name for p in seq[0]["images"]]
    for source, copy in zip(seq[0]["images"], paths):
        copy.write_bytes(Path(source).read_bytes())
    if kind == "truncated":
        paths[index].write_bytes(paths[index].read_bytes()[:2000])
    else:
        paths[index].write_text("this is not an image\n")
    listing = folder / "images.txt"
    listing.write_text("".join(f"{p}\n" for p in paths))
    return listing


@pytest.mark.parametrize("kind, says", [("truncated", "a damaged or truncated PNG file"),
                                        ("text", "not an image format it reads")])
def test_an_unreadable_image_is_skipped_with_its_reason_and_the_run_goes_on(seq, tmp_path, capsys, kind, says):
    listing = corrupted(seq, tmp_path / "in", kind)
    bad = tmp_path / "in" / "images" / "img_003.png"
    out = tmp_path / "o"
    code, stdout, err = run(capsys, "reconstruct", listing, "--calib", seq[1], "--out", out, "--quiet")
    assert code == 0 and "Traceback" not in err, err
    assert f"skipped: {bad}: not a readable image (OpenCV cannot decode it: {says}" in stdout, stdout
    report = json.loads((out / "report.json").read_text())
    row = report["per_image"][3]
    assert row["image"] == "img_003.png" and row["status"] == "failed" and row["failure"] == FailureKind.UNREADABLE
    assert row["reason"].startswith(f"{bad}: not a readable image")
    assert [r["status"] for r in report["per_image"][2:]] == ["registered", "failed", "registered"]
    cameras = json.loads((out / "cameras.json").read_text())["images"]
    assert [c["registered"] for c in cameras] == [True, True, True, False, True]
    assert (cameras[3]["width"], cameras[3]["height"]) == (320, 240)  # its header's, or the size expected
    assert row["reason"] in (out / "report.html").read_text(encoding="utf-8").replace("&#x27;", "'")


def test_a_run_with_an_unreadable_image_resumes_where_it_stopped(seq, tmp_path):
    """Interrupted once the damaged image was skipped, the run resumes from its checkpoint (the
    damaged file is part of the inputs it was made for) and ends as the uninterrupted run."""
    listing = corrupted(seq, tmp_path / "in", "truncated")
    whole = pipeline.reconstruct_to_folder(str(listing), str(seq[1]), tmp_path / "whole")

    def stop_after_the_damaged_image(done, total, message):
        if done == 4:
            raise KeyboardInterrupt

    out = tmp_path / "o"
    with pytest.raises(KeyboardInterrupt):
        pipeline.reconstruct_to_folder(str(listing), str(seq[1]), out, progress=stop_after_the_damaged_image)
    assert (tmp_path / ".o.partial" / pipeline.CHECKPOINT).is_file()
    report = pipeline.reconstruct_to_folder(str(listing), str(seq[1]), out, resume=True)
    assert report["resumed_images"] == ["img_000.png", "img_001.png", "img_002.png", "img_003.png"]
    assert report["per_image"][3] == whole["per_image"][3]
    assert [r["status"] for r in report["per_image"]] == [r["status"] for r in whole["per_image"]]
    got, expected = (json.loads((folder / "cameras.json").read_text())["images"]
                     for folder in (out, tmp_path / "whole"))
    assert [c.get("P") for c in got] == [c.get("P") for c in expected]  # the uninterrupted run's cameras
