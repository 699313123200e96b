"""Runs a user can trust: wrong inputs refused with one line, nothing the user made overwritten,
results written as a whole, interrupted runs resumed (issue 15's cases, on small inputs)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from process_helpers import alive_in_group, wait_until
from cli_helpers import cli_command, one_line_error, run
from scene_helpers import scene_on_disk
from stereoseed.cli import main
from stereoseed.output.result_set import MANIFEST


def _on_disk(scene, folder: Path) -> tuple:
    """The scene's images written to folder / images and a calib.json of its true pair:
    (paths of write_scene, scene, calib.json)."""
    paths, calib = scene_on_disk(scene, folder, images=folder / "images")
    return paths, scene, calib


@pytest.fixture(scope="module")
def seq(tmp_path_factory, box_scene):
    """A 5-image synthetic ring on disk: (paths of write_scene, scene, calib.json with the true pair)."""
    return _on_disk(box_scene.prefix(5), tmp_path_factory.mktemp("seq"))


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory, small_box_scene):
    """A 5-image ring of 320x240 images on disk, as ``seq``: for the tests that run whole
    commands again and again (what they check does not depend on the image size)."""
    return _on_disk(small_box_scene.prefix(5), tmp_path_factory.mktemp("small_seq"))


def reconstruct_args(paths, calib, out, *more):
    return ["reconstruct", paths["images_txt"], "--calib", calib, "--out", out, "--quiet", *more]


# --- wrong inputs that used to give silent garbage -------------------------------------------
@pytest.mark.parametrize("case", ["swapped cameras", "reversed sequence", "same image twice"])
def test_a_calibration_that_does_not_fit_its_images_is_refused(seq, tmp_path, capsys, case):
    paths, scene, calib = seq
    names = [p.name for p in paths["images"]]
    cams = [{"P": P.tolist()} for P in scene.P[:2]]
    if case == "swapped cameras":
        cams = cams[::-1]
    elif case == "reversed sequence":
        names = names[::-1]
    else:
        names = [names[0]] + names
    (tmp_path / "c.json").write_text(json.dumps({"cameras": cams}))
    listing = tmp_path / "list.txt"
    listing.write_text("".join(f"{paths['images_txt'].parent / n}\n" for n in names))
    code, _, err = run(capsys, "reconstruct", listing, "--calib", tmp_path / "c.json", "--out", tmp_path / "o",
                       "--quiet")
    assert code == 2 and one_line_error(err), err
    assert ("does not fit" in err) or ("same image twice" in err)
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o.*"))  # nothing written, no litter


@pytest.mark.parametrize("case", ["points2 reversed", "u and v swapped"])
def test_calibrate_refuses_a_camera_that_cannot_be(seq, tmp_path, capsys, case):
    paths, _, _ = seq
    pts = np.loadtxt(paths["points2"])
    pts = pts[::-1] if case == "points2 reversed" else pts[:, ::-1]
    np.savetxt(tmp_path / "p2.txt", pts)
    code, _, err = run(capsys, "calibrate", paths["pattern"], paths["points1"], tmp_path / "p2.txt",
                       "-o", tmp_path / "c.json")
    assert code == 2 and one_line_error(err) and ("RMS" in err or "behind" in err), err
    assert not (tmp_path / "c.json").exists()


def test_an_image_of_another_size_is_skipped_and_strict_says_so(seq, tmp_path, capsys):
    paths, _, calib = seq
    images = list(paths["images"])
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), cv2.resize(cv2.imread(str(images[3])), (800, 600)))
    listing = tmp_path / "list.txt"
    listing.write_text("".join(f"{p}\n" for p in images[:3] + [big] + images[4:]))
    code, out, _ = run(capsys, *reconstruct_args({"images_txt": listing}, calib, tmp_path / "o", "--strict"))
    assert code == 3
    assert "800x600" in out and out.strip().splitlines()[-1].startswith("registered 4/5 images (1 skipped")
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["per_image"][3]["status"] == "failed"


def test_propagate_refuses_a_calibration_of_another_pair(seq, tmp_path, capsys):
    paths, scene, _ = seq
    (tmp_path / "c.json").write_text(json.dumps({"cameras": [{"P": P.tolist()} for P in scene.P[1::-1]]}))
    code, _, err = run(capsys, "propagate", paths["images"][0], paths["images"][1], "--calib", tmp_path / "c.json",
                       "-o", tmp_path / "p.png")
    assert code == 2 and "does not fit" in err and not (tmp_path / "p.png").exists()


def test_dense_on_the_pair_alone_keeps_its_points_and_says_so(seq, tmp_path, capsys):
    paths, _, calib = seq
    listing = tmp_path / "pair.txt"
    listing.write_text("".join(f"{p}\n" for p in paths["images"][:2]))
    code, out, _ = run(capsys, *reconstruct_args({"images_txt": listing}, calib, tmp_path / "o", "--dense"))
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert code == 0 and report["dense"]["points"] > 10_000 and "off" in report["dense"]["note"]
    assert "no other pair can confirm a point" in out


# --- tracebacks that became one line --------------------------------------------------------
def test_wrong_outputs_and_arguments_are_refused_before_any_work(seq, tmp_path, capsys, monkeypatch):
    from stereoseed import pipeline
    from stereoseed.experiments import demo
    from stereoseed.estimators import calibration
    from stereoseed.io import files as io

    def work_started(*args, **kwargs):
        raise AssertionError("the command started working before refusing its arguments")

    paths, _, calib = seq
    img = paths["images"][0]
    # the first step of each command's work: reading an image, a sequence, calibrating, the demo
    for module, name in ((io, "read_image"), (pipeline, "load_sequence"), (calibration, "calibrate_camera"),
                         (demo, "run_demo")):
        monkeypatch.setattr(module, name, work_started)
    for args in (["match", img, paths["images"][1], "-o", tmp_path / "out.txt"],
                 ["propagate", img, paths["images"][1], "--calib", calib, "-o", tmp_path / "out.txt"],
                 ["demo", "--images", "1", "--out", tmp_path / "d"],
                 ["demo", "--noise", "-1", "--out", tmp_path / "d"],
                 reconstruct_args(paths, calib, tmp_path / "w", "--window", "0"),
                 ["calibrate", paths["pattern"], paths["points1"], paths["points2"], "-o", tmp_path]):
        code, _, err = run(capsys, *args)
        assert code == 2 and one_line_error(err), (args, err)
    assert not list(tmp_path.glob(".*tmp*"))


def test_an_all_zero_camera_is_one_line(seq, tmp_path, capsys):
    paths, _, _ = seq
    (tmp_path / "c.json").write_text(json.dumps({"cameras": [{"P": np.zeros((3, 4)).tolist()}] * 2}))
    code, _, err = run(capsys, *reconstruct_args(paths, tmp_path / "c.json", tmp_path / "o"))
    assert code == 2 and one_line_error(err), err


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("stereoseed ")


# --- data loss and litter -------------------------------------------------------------------
def test_the_results_never_overwrite_what_the_user_made(seq, capsys):
    paths, _, calib = seq
    folder = paths["images_txt"].parent
    before = {p: p.read_bytes() for p in folder.iterdir()}
    code, _, err = run(capsys, *reconstruct_args(paths, calib, folder))
    assert code == 2 and one_line_error(err) and "did not write" in err
    assert {p: p.read_bytes() for p in folder.iterdir()} == before  # the ground-truth cameras.json intact


def test_a_rerun_replaces_the_whole_result_set(small_seq, tmp_path, capsys):
    paths, _, calib = small_seq
    out = tmp_path / "o"
    assert run(capsys, *reconstruct_args(paths, calib, out, "--dense"))[0] == 0
    assert (out / "dense.ply").is_file()
    assert run(capsys, *reconstruct_args(paths, calib, out))[0] == 0  # again, without --dense
    assert not (out / "dense.ply").exists()  # no stale file from the earlier run
    manifest = json.loads((out / MANIFEST).read_text())["files"]
    assert sorted(manifest) == sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != MANIFEST)
    assert not [p for p in tmp_path.iterdir() if p.name != "o"]  # no staging or temp file left
    mask = os.umask(0)
    os.umask(mask)
    assert (out / "cameras.json").stat().st_mode & 0o777 == 0o666 & ~mask


def test_an_output_that_cannot_be_written_is_refused_first(seq, tmp_path, capsys):
    paths, _, calib = seq
    (tmp_path / "file").write_text("x")
    code, _, err = run(capsys, *reconstruct_args(paths, calib, tmp_path / "file"))
    assert code == 2 and "not a folder" in err
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        code, _, err = run(capsys, *reconstruct_args(paths, calib, ro / "o"))
        assert code == 2 and "cannot write" in err


# --- interrupted runs -----------------------------------------------------------------------
def _cameras(out: Path) -> np.ndarray:
    images = json.loads((out / "cameras.json").read_text())["images"]
    return np.array([im["P"] for im in images])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kill test reads /proc")
def test_killed_runs_leave_a_whole_result_set_and_resume_to_the_same_cameras(small_seq, tmp_path):
    paths, _, calib = small_seq
    reference = tmp_path / "reference"
    # a first run compiles what Numba has not cached yet; the runs compared must all be warm (the
    # fastmath alignment kernel differs by ~1e-6 between a fresh compile and its cached code)
    subprocess.run(cli_command(*reconstruct_args(paths, calib, reference, "--dense")), check=True, capture_output=True)
    t = time.perf_counter()
    subprocess.run(cli_command(*reconstruct_args(paths, calib, reference, "--dense")), check=True, capture_output=True)
    full_time = time.perf_counter() - t
    expected = _cameras(reference)
    rng = np.random.default_rng(0)
    out = tmp_path / "o"
    for attempt, fraction in enumerate(rng.uniform(0.3, 0.95, 3)):
        proc = subprocess.Popen(cli_command(*reconstruct_args(paths, calib, out, "--dense")), start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(fraction * full_time)
        os.killpg(proc.pid, signal.SIGKILL) if attempt == 0 else proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert wait_until(lambda: not alive_in_group(proc.pid), 5.0), "a dense worker outlived its parent"
        if out.exists():  # a complete result set, never a mix: every file the manifest lists, nothing else
            listed = json.loads((out / MANIFEST).read_text())["files"]
            assert sorted(listed) == sorted(str(p.relative_to(out)) for p in out.rglob("*")
                                            if p.is_file() and p.name != MANIFEST)
            np.testing.assert_allclose(_cameras(out), expected, atol=1e-9)
        # a killed run's lock file stays (unlocked: the kernel let go of it); the next run takes it over
        assert not [p for p in tmp_path.iterdir() if p.name not in ("reference", "o", ".o.partial", ".o.lock")]
    # a kill of the parent alone once every image is placed (the checkpoint says so), so in the
    # dense stage, whose workers must follow it; then --resume: only the dense stage and the
    # writing are left to do
    proc = subprocess.Popen(cli_command(*reconstruct_args(paths, calib, out, "--dense")), start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoint = tmp_path / ".o.partial" / ".checkpoint.npz"
    wait_until(lambda: proc.poll() is not None or _images_done(checkpoint) == len(paths["images"]), 60.0)
    # the dense stage's workers have started (unless the run is over already)
    wait_until(lambda: proc.poll() is not None or len(alive_in_group(proc.pid)) > 1, 10.0, poll=0.01)
    proc.kill()
    proc.wait()
    assert wait_until(lambda: not alive_in_group(proc.pid), 5.0), "a dense worker outlived its parent"
    t = time.perf_counter()
    done = subprocess.run(cli_command(*reconstruct_args(paths, calib, out, "--dense", "--resume")), capture_output=True,
                          text=True)
    resumed_time = time.perf_counter() - t
    assert done.returncode == 0, done.stderr
    np.testing.assert_allclose(_cameras(out), expected, atol=1e-9)
    assert not (tmp_path / ".o.partial").exists() and not (tmp_path / ".o.lock").exists()
    if proc.returncode == -signal.SIGKILL:  # killed before it finished (it may have won the race)
        # every image came from the checkpoint: the resumed run placed none again (its time is
        # the dense stage's and the writing's; timing belongs in the benchmarks, not here)
        assert len(json.loads((out / "report.json").read_text())["resumed_images"]) == len(paths["images"])
    print(f"uninterrupted {full_time:.1f} s, resumed {resumed_time:.1f} s")


def _images_done(checkpoint: Path) -> int:
    """How many images the checkpoint says are done (0 while there is none, or it is being
    replaced): its JSON part, read as numbers only."""
    import zipfile

    try:
        with np.load(checkpoint, allow_pickle=False) as npz:
            return len(json.loads(npz["meta"].tobytes())["per_image"])
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile):
        return 0
