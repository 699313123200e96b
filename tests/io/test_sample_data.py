"""`stereoseed data fetch` (stereoseed.io.sample_data) against a local HTTP server on 127.0.0.1
serving small archives built here: a tiny templeSparseRing (3 PNGs and a par file) and a tiny
Strecha scene, with the registry pointed at the server. The real servers are not reachable
from the tests."""
from __future__ import annotations

import errno
import functools
import hashlib
import http.server
import stat
import threading
import zipfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from cli_helpers import one_line_error, run
from stereoseed.errors import StereoseedError
from stereoseed.io import sample_data
from stereoseed.io.files import read_middlebury_par
from stereoseed.io.sample_convert import convert_strecha, middlebury_par_text
from stereoseed.io.sample_registry import SETS, Download, SampleSet
from stereoseed.pipeline import load_sequence

REAL_MIRROR = sample_data.offline_mirror()  # before the tests point $STEREOSEED_DATA elsewhere
NAMES = ["templeSR0001.png", "templeSR0002.png", "templeSR0003.png"]


class Server:
    """http.server on 127.0.0.1 (a free port) serving ``folder``; counts the requests."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.requests: list[str] = []
        server = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):  # the test's output stays quiet
                pass

            def send_head(self):
                server.requests.append(self.path)
                return super().send_head()

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                     functools.partial(Handler, directory=str(folder)))
        # a short poll: shutdown() waits for it at every teardown
        self.thread = threading.Thread(target=self.httpd.serve_forever, args=(0.02,), daemon=True)
        self.thread.start()

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_port}/{name}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


@pytest.fixture
def server(tmp_path):
    served = tmp_path / "served"
    served.mkdir()
    s = Server(served)
    yield s
    s.close()


@pytest.fixture(autouse=True)
def no_mirror(tmp_path, monkeypatch):
    """No offline mirror (an empty $STEREOSEED_DATA) and a data folder of the test's own."""
    empty = tmp_path / "no-mirror"
    empty.mkdir()
    monkeypatch.setenv("STEREOSEED_DATA", str(empty))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def tiny_temple_files() -> dict[str, bytes]:
    """Three 80x60 textured PNGs on a ring of cameras and their par file (Middlebury's format)."""
    rng = np.random.default_rng(0)
    files = {}
    cams = {}
    K = np.array([[120.0, 0, 40], [0, 120, 30], [0, 0, 1]])
    for i, name in enumerate(NAMES):
        image = cv2.resize(rng.integers(0, 256, (15, 20, 3), dtype=np.uint8), (80, 60), interpolation=cv2.INTER_NEAREST)
        files[name] = cv2.imencode(".png", image)[1].tobytes()
        a = np.radians(10.0 * i)
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        cams[name] = (K, R, np.array([0.0, 0.0, 0.6]))
    files["templeSR_par.txt"] = middlebury_par_text(cams).encode()
    files["README.txt"] = b"a tiny temple for the tests\n"
    return files


def build_zip(path: Path, members: dict[str, bytes], prefix: str = "templeSparseRing/") -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(prefix + name, data)
        zf.writestr(prefix + "Thumbs.db", b"not part of the set")  # as the published zips carry
    return path


def tiny_temple_set(server: Server, zip_sha: str | None = "auto", files: dict[str, bytes] | None = None,
                    zip_path: Path | None = None) -> SampleSet:
    """The registry's templeSparseRing, pointed at the server: the zip's checksum ("auto": the
    built zip's), the manifest of the tiny files."""
    files = files or tiny_temple_files()
    zip_path = zip_path or build_zip(server.folder / "templeSparseRing.zip", files)
    sha = _sha(zip_path.read_bytes()) if zip_sha == "auto" else zip_sha
    return replace(SETS["templeSparseRing"], downloads=(Download(server.url(zip_path.name), sha, "zip"),),
                   manifest={n: (_sha(d), len(d)) for n, d in files.items()},
                   texts={"ring_order.txt": "".join(f"{n}\n" for n in NAMES)})


def use(monkeypatch, *sets: SampleSet) -> None:
    monkeypatch.setattr(sample_data, "SETS", {**SETS, **{s.name: s for s in sets}})


def files_under(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()] if folder.exists() else []


def test_fetch_from_the_local_server_gives_the_stored_layout(server, monkeypatch, tmp_path, capsys):
    use(monkeypatch, tiny_temple_set(server))
    root = tmp_path / "data"
    code, out, err = run(capsys, "data", "fetch", "templeSparseRing", "--dir", root)
    assert code == 0, err
    folder = root / "templeSparseRing"
    assert f"templeSparseRing: {folder}" in out and "Seitz" in out
    kept = {p.relative_to(folder).as_posix() for p in files_under(folder)}
    assert kept == {*NAMES, "templeSR_par.txt", "README.txt", "ring_order.txt", "SOURCE.txt", sample_data.MARKER}
    assert not (root / sample_data.DOWNLOADS).exists()  # the download is gone once the set is in place
    assert not list(root.glob(".*partial*"))
    images, names, (P1, P2) = load_sequence(str(folder / "ring_order.txt"), str(folder / "templeSR_par.txt"))
    assert names == NAMES and len(images) == 3
    np.testing.assert_allclose(P1, read_middlebury_par(folder / "templeSR_par.txt")[NAMES[0]])
    # fetched once: the second fetch finds it and downloads nothing
    hits = len(server.requests)
    assert sample_data.fetch("templeSparseRing", root) == folder
    assert len(server.requests) == hits == 1


def test_the_default_folder_is_the_users_data_folder(server, monkeypatch, tmp_path):
    use(monkeypatch, tiny_temple_set(server))
    path = sample_data.fetch("templeSparseRing")
    assert path == tmp_path / "xdg" / "stereoseed" / "templeSparseRing"
    assert sample_data.find_sample("templeSparseRing") == path


def test_a_zip_whose_checksum_differs_is_refused_and_nothing_is_left(server, monkeypatch, tmp_path, capsys):
    use(monkeypatch, tiny_temple_set(server, zip_sha="0" * 64))
    root = tmp_path / "data"
    code, out, err = run(capsys, "data", "fetch", "templeSparseRing", "--dir", root)
    assert code == 2 and one_line_error(err) and "SHA-256 differs" in err and "templeSparseRing" in err
    assert files_under(root) == [] and not (root / "templeSparseRing").exists()


def test_a_member_whose_checksum_differs_is_refused_and_nothing_is_left(server, monkeypatch, tmp_path):
    sset = tiny_temple_set(server, zip_sha=None)  # as the Middlebury zips: checked member by member
    manifest = dict(sset.manifest)
    manifest["templeSR0002.png"] = ("f" * 64, manifest["templeSR0002.png"][1])
    use(monkeypatch, replace(sset, manifest=manifest))
    root = tmp_path / "data"
    with pytest.raises(StereoseedError, match=r"templeSR0002.png'? is not the file recorded"):
        sample_data.fetch("templeSparseRing", root)
    assert files_under(root) == []


def test_a_zip_without_checksum_is_accepted_when_its_members_match(server, monkeypatch, tmp_path):
    use(monkeypatch, tiny_temple_set(server, zip_sha=None))
    folder = sample_data.fetch("templeSparseRing", tmp_path / "data")
    assert (folder / "templeSR0003.png").is_file() and not (folder / "Thumbs.db").exists()


@pytest.fixture
def no_unpacking(monkeypatch):
    """Fails the test if any zip member is opened: the refusals below come before extraction."""
    real_open = zipfile.ZipFile.open

    def guarded(self, name, mode="r", *args, **kwargs):
        if mode == "r":
            pytest.fail(f"{name} unpacked")
        return real_open(self, name, mode, *args, **kwargs)  # the test writing its zip

    monkeypatch.setattr(zipfile.ZipFile, "open", guarded)


@pytest.mark.parametrize("evil", ["templeSparseRing/../../escaped.txt", "/tmp/absolute.txt", "..\\escaped.txt"])
def test_a_member_outside_the_folder_is_refused_before_extraction(server, monkeypatch, tmp_path, no_unpacking, evil):
    files = tiny_temple_files()
    path = build_zip(server.folder / "templeSparseRing.zip", files)
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr(evil, b"outside")
    use(monkeypatch, tiny_temple_set(server, files=files, zip_path=path))
    root = tmp_path / "data"
    with pytest.raises(StereoseedError, match="outside the set's folder"):
        sample_data.fetch("templeSparseRing", root)
    assert files_under(tmp_path / "data") == [] and not list(tmp_path.rglob("escaped.txt"))


def test_a_link_member_is_refused(server, monkeypatch, tmp_path, no_unpacking):
    files = tiny_temple_files()
    path = build_zip(server.folder / "templeSparseRing.zip", files)
    link = zipfile.ZipInfo("templeSparseRing/link")
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr(link, "/etc/passwd")
    use(monkeypatch, tiny_temple_set(server, files=files, zip_path=path))
    with pytest.raises(StereoseedError, match="is a link"):
        sample_data.fetch("templeSparseRing", tmp_path / "data")


def test_a_zip_bomb_is_refused_before_extraction(server, monkeypatch, tmp_path, no_unpacking):
    files = tiny_temple_files()
    files["README.txt"] = bytes(8 * 2**20)  # 8 MiB of zeros: deflates about 1000x
    use(monkeypatch, tiny_temple_set(server, files=files))
    with pytest.raises(StereoseedError, match="zip bomb"):
        sample_data.fetch("templeSparseRing", tmp_path / "data")
    assert files_under(tmp_path / "data") == []


def test_a_member_past_the_size_bound_is_refused_before_extraction(server, monkeypatch, tmp_path, no_unpacking):
    use(monkeypatch, tiny_temple_set(server))
    monkeypatch.setattr(sample_data, "MAX_MEMBER_BYTES", 1000)  # the PNGs are larger
    with pytest.raises(StereoseedError, match=r"declares \d+ bytes \(at most 1000\)"):
        sample_data.fetch("templeSparseRing", tmp_path / "data")


def test_a_member_declaring_another_size_than_recorded_is_refused(server, monkeypatch, tmp_path, no_unpacking):
    sset = tiny_temple_set(server)
    manifest = dict(sset.manifest)
    manifest["README.txt"] = (manifest["README.txt"][0], 5)
    use(monkeypatch, replace(sset, manifest=manifest))
    with pytest.raises(StereoseedError, match="the recorded file has 5"):
        sample_data.fetch("templeSparseRing", tmp_path / "data")


def test_a_set_in_the_offline_mirror_is_not_downloaded(server, monkeypatch, tmp_path):
    use(monkeypatch, tiny_temple_set(server))
    mirror = tmp_path / "mirror"
    (mirror / "templeSparseRing").mkdir(parents=True)
    for name, data in tiny_temple_files().items():
        (mirror / "templeSparseRing" / name).write_bytes(data)
    monkeypatch.setenv("STEREOSEED_DATA", str(mirror))
    assert sample_data.fetch("templeSparseRing") == mirror / "templeSparseRing"  # used where it is
    copied = sample_data.fetch("templeSparseRing", tmp_path / "data")  # --dir: copied there
    assert (copied / "templeSR0002.png").read_bytes() == (mirror / "templeSparseRing/templeSR0002.png").read_bytes()
    assert (copied / sample_data.MARKER).is_file() and (copied / "ring_order.txt").is_file()
    assert server.requests == []


def test_an_unreachable_server_is_one_line_and_leaves_nothing(monkeypatch, tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    sset = replace(SETS["templeSparseRing"],
                   downloads=(Download(f"http://127.0.0.1:{port}/templeSparseRing.zip", "0" * 64, "zip"),))
    use(monkeypatch, sset)
    code, out, err = run(capsys, "data", "fetch", "templeSparseRing", "--dir", tmp_path / "data")
    assert code == 2 and one_line_error(err) and "cannot download" in err and str(port) in err
    assert files_under(tmp_path / "data") == []


def test_unknown_name_and_unverifiable_set_are_refused_before_any_download(tmp_path, capsys):
    code, out, err = run(capsys, "data", "fetch", "templeRing", "--dir", tmp_path)
    assert code == 2 and one_line_error(err) and "'templeRing': no such sample set" in err and "templeSparseRing" in err
    # the castle's published images have no checksum recorded yet: refused, nothing fetched
    code, out, err = run(capsys, "data", "fetch", "strechaCastleP19", "--dir", tmp_path)
    assert code == 2 and one_line_error(err) and "no SHA-256 recorded" in err
    assert files_under(tmp_path) == []


def test_every_registered_download_is_checked_by_a_recorded_checksum():
    """A set is fetchable only if every download has its SHA-256, or is a zip whose kept members
    all have theirs; the castle is the one still waiting for its checksums."""
    fetchable = {s.name for s in sample_data.sample_status() if s.fetchable}
    assert fetchable == set(SETS) - {"strechaCastleP19"}
    for s in SETS.values():
        assert all(len(sha) == 64 and size > 0 for sha, size in s.manifest.values())


def test_a_folder_stereoseed_did_not_write_is_left_alone(server, monkeypatch, tmp_path):
    use(monkeypatch, tiny_temple_set(server))
    mine = tmp_path / "data" / "templeSparseRing"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("the user's")
    with pytest.raises(StereoseedError, match="not written by stereoseed"):
        sample_data.fetch("templeSparseRing", tmp_path / "data")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"] and server.requests == []


def test_a_full_disk_is_one_line_and_leaves_nothing(server, monkeypatch, tmp_path, capsys):
    use(monkeypatch, tiny_temple_set(server))

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sample_data, "_unpack", full)
    root = tmp_path / "data"
    code, out, err = run(capsys, "data", "fetch", "templeSparseRing", "--dir", root)
    assert code == 2 and one_line_error(err) and "no space left" in err and "--dir" in err
    assert not (root / "templeSparseRing").exists() and not list(root.glob(".*partial*"))


def test_data_list_says_where_each_set_is(server, monkeypatch, tmp_path, capsys):
    use(monkeypatch, tiny_temple_set(server))
    sample_data.fetch("templeSparseRing", tmp_path / "data")
    code, out, err = run(capsys, "data", "list", "--dir", tmp_path / "data")
    assert code == 0
    assert str(tmp_path / "data" / "templeSparseRing") in out
    assert "absent: stereoseed data fetch dinoSparseRing" in out and "not fetchable yet" in out


# --- the Strecha conversion -------------------------------------------------------------------

def _camera_text(K: np.ndarray, R: np.ndarray, t: np.ndarray, w: int, h: int) -> str:
    """A Strecha .camera file of P = K [R | t]: K, no distortion, camera-to-world R^T, centre."""
    rows = [*K, [0, 0, 0], *R.T, -R.T @ t, [w, h]]
    return "".join(" ".join(f"{v:.12g}" for v in row) + " \n" for row in rows)


def test_strecha_images_and_cameras_become_the_stored_layout(server, monkeypatch, tmp_path):
    rng = np.random.default_rng(1)
    K = np.array([[50.0, 0, 15.5], [0, 51, 7.5], [0, 0, 1]])
    downloads, manifest, truth = [], {}, {}
    for i in range(2):
        name = f"{i:04d}.jpg"
        data = cv2.imencode(".jpg", rng.integers(0, 256, (16, 32, 3), dtype=np.uint8))[1].tobytes()
        (server.folder / name).write_bytes(data)
        R, t = cv2.Rodrigues(np.array([0.0, 0.1 * i, 0.0]))[0], np.array([0.2 * i, 0.0, 3.0])
        (server.folder / f"{name}.camera").write_text(_camera_text(K, R, t, 32, 16))
        truth[name] = K @ np.hstack([R, t[:, None]])
        downloads += [Download(server.url(name), _sha(data), "file", f"full/{name}"),
                      Download(server.url(f"{name}.camera"), _sha((server.folder / f"{name}.camera").read_bytes()),
                               "camera", name)]
        manifest[f"full/{name}"] = (_sha(data), len(data))
    use(monkeypatch, replace(SETS["strechaFountainP11"], downloads=tuple(downloads), manifest=manifest))
    folder = sample_data.fetch("strechaFountainP11", tmp_path / "data")
    full = read_middlebury_par(folder / "full/strechaFountainP11_full_par.txt")
    small = read_middlebury_par(folder / "strechaFountainP11_par.txt")
    S = np.array([[0.25, 0, -0.375], [0, 0.25, -0.375], [0, 0, 1]])  # x' = (x + 0.5) / 4 - 0.5
    for name, P in truth.items():
        np.testing.assert_allclose(full[name], P, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(small[name], S @ P, rtol=1e-9, atol=1e-9)
        assert cv2.imread(str(folder / name)).shape == (4, 8, 3)
    assert (folder / "ring_order.txt").read_text() == "0000.jpg\n0001.jpg\n"


def test_strecha_reduction_reproduces_the_stored_fountain(tmp_path):
    """From the published images in ../shared/data's full/ (cameras written back from its par
    file), the reduced JPEGs are the stored ones byte for byte; two images keep it quick."""
    stored = REAL_MIRROR / "strechaFountainP11"
    if not (stored / "full").is_dir():
        pytest.skip(f"{stored}/full not found; run: stereoseed data fetch strechaFountainP11")
    lines = (stored / "full" / "strechaFountainP11_full_par.txt").read_text().splitlines()[1:]
    par = {f[0]: np.array(f[1:], float) for f in (line.split() for line in lines)}
    (tmp_path / "full").mkdir()
    cameras = {}
    for name in ("0000.jpg", "0005.jpg"):
        (tmp_path / "full" / name).write_bytes((stored / "full" / name).read_bytes())
        K, R, t = par[name][:9].reshape(3, 3), par[name][9:18].reshape(3, 3), par[name][18:]
        cameras[name] = tmp_path / f"{name}.camera"
        cameras[name].write_text(_camera_text(K, R, t, 3072, 2048))
    convert_strecha("strechaFountainP11", tmp_path, cameras, keep_full=False)
    for name in cameras:
        assert (tmp_path / name).read_bytes() == (stored / name).read_bytes()


def test_the_registered_temple_fetched_from_a_zip_of_the_stored_copy_is_the_stored_copy(server, monkeypatch,
                                                                                          tmp_path):
    """The real registry entry (no zip checksum: checked member by member), its URL pointed at a
    zip of ../shared/data's copy laid out as the published zip: every file the copy holds but
    its SOURCE.txt comes out byte for byte (the manifest, the names, ring_order.txt)."""
    stored = REAL_MIRROR / "templeSparseRing"
    if not stored.is_dir():
        pytest.skip(f"{stored} not found; run: stereoseed data fetch templeSparseRing")
    ours = {"SOURCE.txt", "ring_order.txt"}  # written by stereoseed, not in the published zip
    with zipfile.ZipFile(server.folder / "templeSparseRing.zip", "w") as zf:
        for p in sorted(stored.iterdir()):
            if p.name not in ours:
                zf.write(p, f"templeSparseRing/{p.name}")
    sset = SETS["templeSparseRing"]
    use(monkeypatch, replace(sset, downloads=(replace(sset.downloads[0], url=server.url("templeSparseRing.zip")),)))
    folder = sample_data.fetch("templeSparseRing", tmp_path / "data")
    for p in stored.iterdir():
        if p.name != "SOURCE.txt":
            assert (folder / p.name).read_bytes() == p.read_bytes(), p.name


def test_fetching_into_the_mirror_itself_uses_it(server, monkeypatch, tmp_path, capsys):
    use(monkeypatch, tiny_temple_set(server))
    mirror = tmp_path / "mirror"
    (mirror / "templeSparseRing").mkdir(parents=True)
    monkeypatch.setenv("STEREOSEED_DATA", str(mirror))
    code, out, err = run(capsys, "data", "fetch", "templeSparseRing", "--dir", mirror)
    assert code == 0 and "nothing downloaded" in out and server.requests == []
