"""`stereoseed export` under hostile input: a result folder damaged or edited by hand (a
truncated or altered tracks.npz, a cameras.json missing images, a NaN camera, image names no
format can hold) and an output folder holding the user's files. Every case is one line or a
valid model; nothing the user wrote is overwritten; nothing in the folder is ever unpickled."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from cli_helpers import one_line_error
from scene_helpers import scene_on_disk
from stereoseed.cli import main
from stereoseed.errors import StereoseedError
from stereoseed.output.reader import load_result
from stereoseed.pipeline import reconstruct_to_folder


@pytest.fixture(scope="module")
def result(tmp_path_factory, small_box_scene) -> Path:
    """A result folder of the 5-image 320x240 ring."""
    folder = tmp_path_factory.mktemp("export_faults")
    paths, calib = scene_on_disk(small_box_scene.prefix(5), folder, images=folder / "images")
    reconstruct_to_folder(str(paths["images_txt"]), str(calib), folder / "result")
    return folder / "result"


@pytest.fixture
def copy(result, tmp_path) -> Path:
    """A copy of the result folder to damage."""
    return Path(shutil.copytree(result, tmp_path / "result"))


def export(capsys, folder, out, *more) -> tuple[int, str]:
    code = main(["export", str(folder), "--out", str(out), *map(str, more)])
    return code, capsys.readouterr().err


def edit_cameras(folder: Path, edit) -> None:
    path = folder / "cameras.json"
    cams = json.loads(path.read_text())
    edit(cams["images"])
    path.write_text(json.dumps(cams))


def edit_tracks(folder: Path, edit) -> None:
    path = folder / "tracks.npz"
    with np.load(path) as npz:
        tracks = {k: npz[k] for k in npz.files}
    edit(tracks)
    np.savez(path, **tracks)


# --- 6. a damaged result folder is one line ------------------------------------------------------------
def test_a_truncated_tracks_file_is_one_line(copy, tmp_path, capsys):
    data = (copy / "tracks.npz").read_bytes()
    (copy / "tracks.npz").write_bytes(data[: len(data) // 2])
    code, err = export(capsys, copy, tmp_path / "model")
    assert code == 2 and one_line_error(err) and "tracks.npz" in err, err
    assert not (tmp_path / "model").exists()


def test_a_zip_bomb_tracks_file_is_refused_before_it_is_decompressed(copy, tmp_path, capsys, monkeypatch):
    """Issue 48 row 9: a tracks.npz whose point_xyz inflates ~1000-fold (here 96 MiB of zeros behind
    a valid .npy header; 4.5 GB in the report) was decompressed whole before it was validated."""
    import zipfile

    with np.load(copy / "tracks.npz") as npz:
        tracks = {k: npz[k] for k in npz.files}
    rows = 2**22  # 96 MiB of float64 (x, y, z)
    with zipfile.ZipFile(copy / "tracks.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        for name, array in tracks.items():
            if name != "point_xyz":
                with zf.open(f"{name}.npy", "w") as f:
                    np.lib.format.write_array(f, array)
        with zf.open("point_xyz.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (rows, 3)})
            zeros = bytes(2**20)
            for _ in range(rows * 24 // len(zeros)):
                f.write(zeros)
    assert (copy / "tracks.npz").stat().st_size < 1_000_000
    inflated = []
    real = zipfile.ZipExtFile.read
    monkeypatch.setattr(zipfile.ZipExtFile, "read", lambda self, n=-1: inflated.append(self.name) or real(self, n))
    code, err = export(capsys, copy, tmp_path / "out")
    assert code == 2 and one_line_error(err) and "tracks.npz: its arrays declare" in err
    assert "point_xyz.npy" not in inflated


def test_a_cameras_file_missing_images_is_one_line(copy, tmp_path, capsys):
    edit_cameras(copy, lambda images: images.pop())
    code, err = export(capsys, copy, tmp_path / "model")
    assert code == 2 and one_line_error(err) and "cameras.json" in err, err


@pytest.mark.parametrize("damage", [
    "obs_image out of range", "obs_point out of range", "obs_keypoint out of range", "negative index",
    "keypoints_offset not increasing", "float indices", "rgb as float", "point NaN", "missing array",
    "wrong shape", "keypoint observed twice", "unregistered image observed", "newer format",
])
def test_every_array_is_checked_against_cameras_json(copy, tmp_path, capsys, damage):
    def edit(tr):
        if damage == "obs_image out of range":
            tr["obs_image"][0] = 99
        elif damage == "obs_point out of range":
            tr["obs_point"][0] = len(tr["point_xyz"])
        elif damage == "obs_keypoint out of range":
            tr["obs_keypoint"][0] = 10 ** 6
        elif damage == "negative index":
            tr["obs_point"][0] = -1
        elif damage == "keypoints_offset not increasing":
            tr["keypoints_offset"][2] = tr["keypoints_offset"][1] - 1
        elif damage == "float indices":
            tr["obs_image"] = tr["obs_image"].astype(float)
        elif damage == "rgb as float":
            tr["point_rgb"] = tr["point_rgb"].astype(float)
        elif damage == "point NaN":
            tr["point_xyz"][0, 0] = np.nan
        elif damage == "missing array":
            del tr["obs_keypoint"]
        elif damage == "wrong shape":
            tr["point_xyz"] = tr["point_xyz"][:, :2]
        elif damage == "keypoint observed twice":
            tr["obs_keypoint"][1], tr["obs_image"][1] = tr["obs_keypoint"][0], tr["obs_image"][0]
        elif damage == "unregistered image observed":
            pass  # cameras.json below
        else:
            tr["format_version"] = np.array(99)

    edit_tracks(copy, edit)
    if damage == "unregistered image observed":
        edit_cameras(copy, lambda images: images[2].update(registered=False))
    with pytest.raises(StereoseedError) as e:
        load_result(copy)
    assert len(str(e.value).splitlines()) == 1 and str(e.value).startswith(str(copy))
    code, err = export(capsys, copy, tmp_path / "model")
    assert code == 2 and one_line_error(err)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.one_of(st.none(), st.integers(0, 10 ** 6)),
       flips=st.lists(st.tuples(st.integers(0, 10 ** 6), st.integers(0, 255)), max_size=4))
def test_any_damage_to_tracks_is_refused_or_read_as_a_valid_model(result, tmp_path_factory, cut, flips):
    folder = Path(tmp_path_factory.mktemp("fuzz"))
    shutil.copy(result / "cameras.json", folder)
    data = bytearray((result / "tracks.npz").read_bytes())
    for pos, value in flips:
        data[pos % len(data)] = value
    (folder / "tracks.npz").write_bytes(bytes(data[:cut]) if cut is not None else bytes(data))
    try:
        loaded = load_result(folder)
    except StereoseedError as e:
        assert len(str(e).splitlines()) == 1 and str(e).startswith(str(folder))
        return
    from stereoseed.output.export import write_colmap

    write_colmap(loaded, folder / "model")  # whatever was read, every export can write it


# --- 7. names and cameras no format can hold -------------------------------------------------------------
@pytest.mark.parametrize("fmt, name, says", [
    ("colmap", "a\nb.png", "line break"), ("colmap", "a\x1bb.png", "control character"),
    ("colmap", "with space.png", "a space"), ("nvm", "with space.png", "a space"),
    ("bundler", "trail.png ", "space at its start"), ("colmap-binary", "nul\x00.png", "control character"),
    ("colmap", "img_000.png", "another image"),
])
def test_a_name_the_format_cannot_hold_is_refused_naming_the_image(copy, tmp_path, capsys, fmt, name, says):
    edit_cameras(copy, lambda images: images[3].update(name=name))
    args = {"colmap": [], "colmap-binary": ["--binary"], "nvm": ["--format", "nvm"],
            "bundler": ["--format", "bundler"]}[fmt]
    code, err = export(capsys, copy, tmp_path / "model", *args)
    assert code == 2 and one_line_error(err) and says in err, err
    assert repr(name)[1:-1][:20] in err and not (tmp_path / "model").exists()
    if fmt == "colmap" and name == "with space.png":  # COLMAP's binary model holds it, and the message says so
        assert "--binary" in err and export(capsys, copy, tmp_path / "model", "--binary")[0] == 0
        pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) is the COLMAP oracle")
        assert name in {im.name for im in pycolmap.Reconstruction(str(tmp_path / "model")).images.values()}


def test_a_camera_that_is_not_finite_is_left_out_with_a_warning(copy, tmp_path, capsys):
    edit_cameras(copy, lambda images: images[3].update(P=[[float("nan")] * 4] * 3))
    code, err = export(capsys, copy, tmp_path / "model")
    assert code == 0 and "img_003.png" in err and "left out" in err, err
    text = (tmp_path / "model" / "cameras.txt").read_text() + (tmp_path / "model" / "images.txt").read_text()
    assert "nan" not in text.lower() and "img_003.png" not in text
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) is the COLMAP oracle")
    model = pycolmap.Reconstruction(str(tmp_path / "model"))
    assert len(model.images) == 4 and all(p.track.length() >= 1 for p in model.points3D.values())


# --- 4. the export's output folder ---------------------------------------------------------------------
@pytest.mark.parametrize("fmt, mine", [("colmap", "cameras.txt"), ("nvm", "model.nvm"), ("bundler", "list.txt")])
def test_an_export_never_overwrites_the_users_files(result, tmp_path, capsys, fmt, mine):
    """Issue 48's rule: --force writes beside the user's files, never over them: a file of one of
    the export's names that it did not write is refused with it too, byte for byte left."""
    out = tmp_path / "model"
    out.mkdir()
    (out / mine).write_text("my own model")
    code, err = export(capsys, result, out, "--format", fmt)
    assert code == 2 and one_line_error(err) and mine in err and "--force" in err, err
    assert sorted(p.name for p in out.iterdir()) == [mine] and (out / mine).read_text() == "my own model"
    code, err = export(capsys, result, out, "--format", fmt, "--force")
    assert code == 2 and one_line_error(err) and f"{out / mine}: stereoseed export did not write it" in err, err
    assert sorted(p.name for p in out.iterdir()) == [mine] and (out / mine).read_text() == "my own model"
    (out / mine).rename(out / "notes.txt")  # another name: --force writes beside it
    assert export(capsys, result, out, "--format", fmt, "--force")[0] == 0
    assert (out / "notes.txt").read_text() == "my own model" and (out / mine).is_file()
    assert export(capsys, result, out, "--format", fmt, "--force")[0] == 0  # its own: replaced


def test_an_export_replaces_its_own_files_and_no_others(result, tmp_path, capsys):
    out = tmp_path / "model"
    for fmt in ("colmap", "nvm", "bundler", "colmap"):  # again into the folder it wrote
        assert export(capsys, result, out, "--format", fmt)[0] == 0
    (out / "notes.txt").write_text("mine")
    code, err = export(capsys, result, out)
    assert code == 2 and "notes.txt" in err and (out / "notes.txt").read_text() == "mine"
    assert not [p for p in out.iterdir() if ".tmp" in p.name]


def test_an_export_into_the_result_folder_is_refused(copy, capsys):
    before = sorted(p.name for p in copy.iterdir())
    code, err = export(capsys, copy, copy)
    assert code == 2 and one_line_error(err)
    assert sorted(p.name for p in copy.iterdir()) == before


def test_a_text_export_over_a_binary_one_leaves_no_stale_bin_files(result, tmp_path, capsys):
    """Issue 48 row 10: COLMAP reads a folder's .bin model before its .txt one, so the binary
    export the folder held before would have been read instead of the new text one."""
    out = tmp_path / "m"
    assert export(capsys, result, out, "--binary")[0] == 0
    assert export(capsys, result, out)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == [".stereoseed-export.json", "cameras.txt", "images.txt",
                                                     "points3D.txt"]
    assert sorted(json.loads((out / ".stereoseed-export.json").read_text())["files"]) == [
        "cameras.txt", "images.txt", "points3D.txt"]
    assert export(capsys, result, out, "--binary")[0] == 0
    assert sorted(p.suffix for p in out.iterdir() if p.suffix in (".txt", ".bin")) == [".bin"] * 3
    theirs = tmp_path / "theirs"  # a binary model the export did not write: never removed, even with --force
    theirs.mkdir()
    (theirs / "cameras.bin").write_bytes(b"their model")
    code, err = export(capsys, result, theirs, "--force")
    assert code == 2 and one_line_error(err) and "cameras.bin: a COLMAP model stereoseed export did not write" in err
    assert sorted(p.name for p in theirs.iterdir()) == ["cameras.bin"]
