import json

import numpy as np
import pytest

from stereoseed.geometry.projection import camera_center
from stereoseed import cli
from stereoseed.cli import main
from stereoseed.synthetic.scene import write_scene
from cli_helpers import run


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory, box_scene):
    return write_scene(box_scene, tmp_path_factory.mktemp("scene")), box_scene


def test_calibrate_writes_calib_json(scene_files, tmp_path, capsys):
    paths, scene = scene_files
    out = tmp_path / "new" / "calib.json"
    assert main(["calibrate", str(paths["pattern"]), str(paths["points1"]), str(paths["points2"]), "-o", str(out)]) == 0
    cams = json.loads(out.read_text())["cameras"]
    assert len(cams) == 2 and all(set(c) >= {"P", "K", "R", "t", "rms_px"} for c in cams)
    for i, c in enumerate(cams):
        assert np.linalg.norm(camera_center(np.array(c["P"])) - camera_center(scene.P[i])) < 0.01
    assert "reprojection RMS" in capsys.readouterr().out


@pytest.mark.parametrize("bad", ["missing", "columns", "length", "few", "coplanar", "nan"])
def test_calibrate_bad_input_one_line_exit_2(scene_files, tmp_path, capsys, bad):
    paths, _ = scene_files
    pattern = np.loadtxt(paths["pattern"])
    pts1 = np.loadtxt(paths["points1"])
    pat_file, p1_file = tmp_path / "pattern.txt", tmp_path / "p1.txt"
    if bad == "columns":
        pattern = pattern[:, :2]
    elif bad == "length":
        pts1 = pts1[:-3]
    elif bad == "few":
        pattern, pts1 = pattern[:5], pts1[:5]
    elif bad == "coplanar":
        pattern = pattern.copy()
        pattern[:, 2] = 0.0
    np.savetxt(pat_file, pattern)
    np.savetxt(p1_file, pts1)
    if bad == "nan":
        p1_file.write_text(p1_file.read_text().replace("\n", "\nnan 1\n", 1))
    if bad == "missing":
        p1_file = tmp_path / "does-not-exist.txt"
    code = main(["calibrate", str(pat_file), str(p1_file), str(paths["points2"]), "-o", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("stereoseed: error: ") and err.count("\n") == 1
    assert "Traceback" not in err
    assert not (tmp_path / "c.json").exists()


def test_reconstruct_bad_inputs(tmp_path, capsys, scene_files):
    paths, _ = scene_files
    assert main(["reconstruct", str(tmp_path / "nothing"), "--calib", "x.json", "--out", str(tmp_path / "o")]) == 2
    assert "not found" in capsys.readouterr().err
    bad = tmp_path / "calib.json"
    bad.write_text('{"cameras": [{"P": [[1, 0, 0, 0]]}]}')
    assert main(["reconstruct", str(paths["images_txt"]), "--calib", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "give both cameras of the pair" in capsys.readouterr().err


def test_the_command_exits_with_mains_code_after_freezing_the_collector(tmp_path, capsys, monkeypatch):
    frozen = []
    monkeypatch.setattr(cli.gc, "freeze", lambda: frozen.append(True))  # not this test process's collector
    monkeypatch.setattr("sys.argv", ["stereoseed", "reconstruct", str(tmp_path / "nothing"), "--calib", "x.json",
                                     "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit) as exit_:
        cli.run()
    assert exit_.value.code == 2 and frozen == [True]
    assert "not found" in capsys.readouterr().err


def test_match_on_a_textureless_image_warns_in_one_line(tmp_path, capsys, scene_files):
    import cv2
    import warnings

    paths, _ = scene_files
    flat = tmp_path / "flat.png"
    cv2.imwrite(str(flat), np.full((480, 640, 3), 128, np.uint8))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(["match", str(paths["images"][0]), str(flat), "-o", str(tmp_path / "m.png")])
    err = capsys.readouterr().err
    assert code == 0 and (tmp_path / "m.png").exists()
    assert err and all(line.startswith("stereoseed: warning: ") for line in err.strip().splitlines()), err


def test_demo_runs_end_to_end_and_reports_against_the_truth(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--images", "4"]) == 0
    printed = capsys.readouterr().out
    assert "registered 4/4 images" in printed and "quasi-dense" in printed
    report = json.loads((out / "report.json").read_text())
    assert report["registered"] == 4 and report["dense"]["points"] > 100_000
    assert report["ground_truth"]["corners_rms_3d_m"] < 0.005  # pair calibrated from 0.13 px pattern pixels
    assert report["dense"]["median_surface_distance_m"] < 0.002
    for name in ("cameras.json", "sparse.ply", "dense.ply", "calib.json"):
        assert (out / name).is_file()


def test_a_first_run_says_it_compiles_the_kernels_first(tmp_path, capsys, monkeypatch, small_box_scene):
    """After a fresh install the first run compiles the Numba kernels: it says so once on stderr
    before any work, with how long it takes, also under --quiet (a quiet run that seems to hang
    is worse). The check reads Numba's cache index."""
    from stereoseed import precompile
    from stereoseed.cli import _progress
    from stereoseed.features.edge_corners import _edge_corner_kernel
    from stereoseed.features.harris import extract_features

    small = small_box_scene.prefix(2)
    extract_features(small.images[0])  # its corners call the kernel: compiled and cached if they were not
    assert _edge_corner_kernel.signatures and precompile.kernels_cached() is True
    monkeypatch.setattr(_edge_corner_kernel._cache._cache_file, "_index_path", str(tmp_path / "none.nbi"))
    assert precompile.kernels_cached() is False  # an empty cache, as after a fresh install
    args = ["reconstruct", str(tmp_path / "no_images"), "--calib", str(tmp_path / "calib.json"),
            "--out", str(tmp_path / "out")]
    monkeypatch.setattr(_progress, "_said", False)  # a fresh process
    assert main(args + ["--quiet"]) != 0  # the input is refused, the notice came first
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("stereoseed: compiling the") and "first run on this installation" in err[0]
    assert "stereoseed precompile" in err[0] and " s " in err[0]  # what to do ahead, and how long
    assert main(args) != 0
    assert "compiling" not in capsys.readouterr().err  # said once a process


def test_the_demo_takes_the_result_folders_lock(tmp_path, capsys):
    from stereoseed.output.result_set import ResultSet

    out = tmp_path / "demo"
    with ResultSet(out):  # as another run writing there
        assert main(["demo", "--images", "4", "--sparse", "--out", str(out)]) == 2
    assert "another stereoseed run is writing" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_the_top_level_help_describes_the_workflow(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    out = capsys.readouterr().out
    assert done.value.code == 0 and "workflow:" in out and "Command-line interface" not in out
    steps = out[out.index("workflow:"):]
    order = [steps.index(f"stereoseed {c} ") for c in ("target", "calibrate", "reconstruct", "view", "export")]
    assert order == sorted(order)
    commands = set(cli.build_parser()._subparsers._group_actions[0].choices)
    named = {line.split("stereoseed ")[1].split()[0] for line in steps.splitlines()
             if "stereoseed " in line and "COMMAND" not in line and "stereoseed." not in line}
    assert named <= commands and {"calibrate", "reconstruct", "view", "export"} <= named  # only commands that exist


def test_config_prints_the_resolved_configuration_as_toml(capsys):
    import tomllib

    from stereoseed.config import Config

    assert main(["config", "--mode", "paper"]) == 0
    shown = tomllib.loads(capsys.readouterr().out)
    assert shown["pipeline"]["camera_model"] == "free" and shown["matching"]["first_pass_ratio"] == "none"
    assert Config.from_dict(shown).resolve() == Config().with_mode("paper").resolve()


def _unchanged(paths) -> dict:
    return {p: p.read_bytes() for p in paths}


def test_no_writer_writes_over_its_input(scene_files, tmp_path, capsys):
    """Issue 48 row 3: an output, given (-o, --out) or derived (calibrate's <stem>_target.json),
    that is one of the command's inputs is refused in one line before any work; the input stays."""
    from cli_helpers import one_line_error

    paths, _ = scene_files
    points = tmp_path / "p1.txt"
    points.write_bytes(paths["points1"].read_bytes())
    target = tmp_path / "calib_target.json"
    target.write_text("{}")
    image = tmp_path / "a.png"
    image.write_bytes(paths["images"][0].read_bytes())
    link = tmp_path / "hard.png"  # another name of the same image
    link.hardlink_to(image)
    before = _unchanged([points, target, image])
    for args, says in (
            (["calibrate", paths["pattern"], points, paths["points2"], "-o", points], f"{points}: is also an input"),
            (["calibrate", "--target", target, image, image, "-o", tmp_path / "calib.json"],
             f"{target}: is also an input"),
            (["calibrate", "--target", tmp_path / "t.json", image, image, "--intrinsics1", tmp_path / "c.yaml", "-o",
              tmp_path / "c.yaml"], "is also an input"),
            (["intrinsics", image, "--target", target, "-o", target], "is also an input"),
            (["match", image, paths["images"][1], "-o", link], f"{link}: is also an input ({image})"),
            (["export", tmp_path, "--format", "colmap", "--out", tmp_path], "is also an input"),
            # the derived name on a file of the user's that is no input: their target, say, copied there
            (["calibrate", "--target", tmp_path / "t.json", image, image, "-o", tmp_path / "calib.json"],
             f"{target}: exists and stereoseed did not write it")):
        code, _, err = run(capsys, *args)
        assert code == 2 and one_line_error(err) and says in err, (args, err)
    assert _unchanged([points, target, image]) == before
    assert not (tmp_path / "calib.json").exists()
    from stereoseed.api import REFINED_TARGET_NOTE
    from stereoseed.io.outputs import record_written_file

    # the refined target's note is no proof: the user's copy of an earlier one, edited, holds it too
    target.write_text(json.dumps({"unit": "mm", "note": REFINED_TARGET_NOTE, "faces": []}))
    code, _, err = run(capsys, "calibrate", "--target", tmp_path / "t.json", image, image, "-o", tmp_path / "calib.json")
    assert code == 2 and f"{target}: exists and stereoseed did not write it" in err, err
    record_written_file(target)  # as an earlier calibrate did once it wrote it: its to replace
    code, _, err = run(capsys, "calibrate", "--target", tmp_path / "t.json", image, image, "-o", tmp_path / "calib.json")
    assert code == 2 and "t.json: target file not found" in err  # past the check: the next refusal


def test_a_check_image_never_lands_on_a_photo(tmp_path):
    """calibrate's check image of photo 7.jpg is <stem of -o>_cam1_7.png: a photo of that name
    gets another one."""
    from stereoseed.cli.calibration import _unique_png

    out = tmp_path / "calib.json"
    photo = tmp_path / "calib_cam1_7.png"
    photo.write_bytes(b"a photo")
    taken: set[str] = set()
    assert _unique_png(out, 1, "x/7.jpg", taken, [photo, out]) == tmp_path / "calib_cam1_7_2.png"
    assert _unique_png(out, 1, "y/7.jpg", taken, [photo, out]) == tmp_path / "calib_cam1_7_3.png"
    assert _unique_png(out, 2, "7.jpg", taken, [photo, out]) == tmp_path / "calib_cam2_7.png"


@pytest.mark.parametrize("how", ["one point", "one line"])
def test_calibrate_refuses_degenerate_typed_points(scene_files, tmp_path, capsys, how):
    """Issue 48 row 4: every pixel alike (or all on one line) gave an all-NaN camera, RMS nan,
    exit 0; now one line naming the file, exit 2, nothing written (with --lens too: a traceback)."""
    from cli_helpers import one_line_error

    paths, _ = scene_files
    pixels = np.loadtxt(paths["points1"])
    same = tmp_path / "same.txt"
    if how == "one point":
        np.savetxt(same, np.full_like(pixels, 100.0))
    else:
        np.savetxt(same, np.c_[pixels[:, 0], 2 * pixels[:, 0] + 7])
    for lens in ([], ["--lens"]):
        code, _, err = run(capsys, "calibrate", paths["pattern"], same, paths["points2"], "-o", tmp_path / "c.json",
                           *lens)
        where = "at one point" if how == "one point" else "on one line"
        assert code == 2 and one_line_error(err) and f"{same}: the {len(pixels)} pixels lie {where}" in err, err
        assert not (tmp_path / "c.json").exists()


def test_a_reader_that_stops_reading_is_no_error_of_the_command():
    """Issue 48 row 12: `stereoseed ... | head -1` exited 2 ("Broken pipe") after its work was
    done; the pipe's reader is gone before the command writes a line here."""
    import subprocess

    from cli_helpers import cli_command

    child = subprocess.Popen(cli_command("config"), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    child.stdout.close()
    try:
        err = child.stderr.read().decode()
        assert child.wait(timeout=60) == 0 and err == ""
    finally:
        child.stderr.close()
        if child.poll() is None:
            child.kill()


def test_a_warning_during_a_progress_bar_is_a_line_of_its_own(monkeypatch):
    """The bar is drawn on stderr without a newline: a warning (the CLI's or the library's) clears
    it and takes a line of its own, the bar drawn again below it."""
    import io
    import logging
    import sys

    from stereoseed.cli import _progress
    from stereoseed.cli._terminal import LibraryLines, warn

    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    library = logging.getLogger("stereoseed.test_lines")
    handler = LibraryLines(logging.WARNING)
    library.addHandler(handler)
    try:
        with _progress.Bar("image", quiet=False) as bar:
            bar(1, 4, "a.png")
            warn("the first warning")
            library.warning("a library warning")
            bar(2, 4, "b.png")
    finally:
        library.removeHandler(handler)
    text = err.getvalue()
    for line in ("stereoseed: warning: the first warning", "stereoseed: WARNING: a library warning"):
        before = text.split(line)[0]
        assert before[-1:] in ("\r", "\n"), repr(before[-40:])  # not after the bar's text
        assert text.split(line)[1].startswith("\n")
