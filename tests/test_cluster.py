"""Jobs on a Dask cluster (issue 19): the dense stage and `stereoseed batch` against a real local
cluster of two worker processes on the loopback interface; the local pool; the sequence list."""
import json
import os
import re
import socket
import sys
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
from distributed import Client, LocalCluster

from cli_helpers import one_line_error
from process_helpers import alive_in_group, wait_until
from scene_helpers import scene_on_disk
from stereoseed.batch import read_sequence_list, run_batch
from stereoseed.cli import main
from stereoseed.cluster import JobPool, executor_for
from stereoseed.config import Config
from stereoseed.dense.densify import densify
from stereoseed.errors import StereoseedError
from stereoseed.pipeline import reconstruct
from stereoseed.io.ply import read_ply_vertices


@pytest.fixture(scope="module")
def scheduler():
    """The address of a two-worker Dask cluster (one thread each, separate processes)."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        yield cluster.scheduler_address


@pytest.fixture(scope="module")
def four_views(small_box_scene):
    """Four 320x240 views of the textured box: three dense pairs (what the cluster tests check
    does not depend on the image size; small images keep their many whole runs short)."""
    return small_box_scene.prefix(4)


@pytest.fixture(scope="module")
def sequence_files(tmp_path_factory, four_views):
    """The scene on disk as `reconstruct` reads it: images, images.txt (four), first3.txt (three),
    calib.json (the pair's true cameras)."""
    folder = tmp_path_factory.mktemp("seq")
    scene_on_disk(four_views, folder)
    (folder / "first3.txt").write_text("".join(f"{n}\n" for n in four_views.names[:3]))
    return folder


def _workers(scheduler: str) -> set[str]:
    with Client(scheduler, set_as_default=False) as client:
        return set(client.scheduler_info()["workers"])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dense_on_the_cluster_is_the_local_cloud(scheduler, four_views, tmp_path):
    """The pair jobs are deterministic and fused in pair order: the same file either way."""
    cfg = Config().replace(trust={"keep_flagged": True})  # every consecutive pair, flagged or not
    recon, _ = reconstruct(four_views.images, four_views.names, four_views.P[:2], cfg)
    assert len(recon.registered_views) == 4
    for name in ("local", "remote"):
        (tmp_path / name).mkdir()
    workers = _workers(scheduler)
    _, local = densify(recon, cfg, tmp_path / "local")
    with executor_for(scheduler, cfg.dense.pool_size()) as pool:
        assert pool.remote and pool.slots == 2
        _, remote = densify(recon, cfg, tmp_path / "remote", pool)
    assert _workers(scheduler) == workers  # none died (Dask would rerun its job quietly on a new one)
    assert remote["points"] == local["points"] > 30_000  # measured 65,908
    assert [p["wide_angle"] for p in remote["pairs"]] == [p["wide_angle"] for p in local["pairs"]]
    assert [p["pair"] for p in remote["pairs"]] == [[a, b] for a, b in zip(four_views.names, four_views.names[1:])]
    a, b = read_ply_vertices(tmp_path / "local" / "dense.ply"), read_ply_vertices(tmp_path / "remote" / "dense.ply")
    np.testing.assert_array_equal(a, b)  # positions, colours, normals, support


def test_batch_on_the_cluster_reports_the_bad_sequence_and_writes_the_others(scheduler, sequence_files, tmp_path,
                                                                             capsys):
    seq = sequence_files
    listing = tmp_path / "sequences.txt"
    listing.write_text(f"# IMAGES CALIB OUT\n"
                       f"{seq}/images.txt {seq}/calib.json four   # the whole ring\n"
                       f"{seq}/images.txt {seq}/missing.json bad\n"
                       f"\n"
                       f"{seq}/first3.txt {seq}/calib.json three\n")
    workers = _workers(scheduler)
    code = main(["batch", str(listing), "--dense", "--scheduler", scheduler, "--out-root", str(tmp_path / "res"),
                 "--quiet"])
    out = capsys.readouterr().out
    assert code == 1
    assert _workers(scheduler) == workers  # the failed sequence failed in its job, no worker died
    lines = out.strip().splitlines()
    assert lines[0].startswith("four: registered 4/4 images")
    assert lines[1].startswith("bad: failed: ") and "missing.json: calibration file not found" in lines[1]
    assert lines[2].startswith("three: registered 3/3 images")
    assert lines[3].startswith("batch: 2 of 3 sequences reconstructed; failed: bad (")
    res = tmp_path / "res"
    assert sorted(p.name for p in res.iterdir()) == ["four", "three"]  # no staging folder left behind

    # each folder is what `reconstruct --dense` writes on this machine
    for name, images in (("four", "images.txt"), ("three", "first3.txt")):
        assert main(["reconstruct", str(seq / images), "--calib", str(seq / "calib.json"), "--dense",
                     "--out", str(tmp_path / f"local_{name}"), "--quiet"]) == 0
        got, want = (json.loads((d / "cameras.json").read_text())["images"] for d in (res / name, tmp_path / f"local_{name}"))
        assert [c["name"] for c in got] == [c["name"] for c in want]
        for c, w in zip(got, want):
            assert c["registered"] and w["registered"]
            np.testing.assert_allclose(c["P"], w["P"], rtol=1e-9, atol=1e-9)
        dense_got = read_ply_vertices(res / name / "dense.ply")
        dense_want = read_ply_vertices(tmp_path / f"local_{name}" / "dense.ply")
        assert len(dense_got) == len(dense_want) > 20_000  # measured 43,313 (four)
        report = json.loads((res / name / "report.json").read_text())
        assert report["dense"]["points"] == len(dense_got)
        assert report["config"]["dense"]["workers"] == 1  # a Dask worker runs its pairs itself


def test_batch_locally_runs_every_sequence_in_list_order(sequence_files, tmp_path):
    seq = sequence_files
    listing = tmp_path / "list.txt"
    listing.write_text(f"{seq}/first3.txt {seq}/calib.json a\n{seq}/first3.txt {seq}/nothing.txt b\n")
    seen = []
    outcomes = run_batch(read_sequence_list(listing), Config(), progress=lambda d, t, m: seen.append((d, t, m)))
    assert [o.ok for o in outcomes] == [True, False]
    assert outcomes[0].summary["registered"] == 3 and outcomes[0].summary["points"] > 100
    assert "nothing.txt: calibration file not found" in outcomes[1].reason
    assert seen == [(0, 2, "running in this process"), (1, 2, "a: done"), (2, 2, "b: failed")]
    assert (tmp_path / "a" / "cameras.json").is_file() and not (tmp_path / "b").exists()


def test_unreachable_scheduler_is_one_line_naming_it(sequence_files, tmp_path, capsys):
    address = f"tcp://127.0.0.1:{_free_port()}"
    seq = sequence_files
    code = main(["reconstruct", str(seq / "images.txt"), "--calib", str(seq / "calib.json"), "--dense",
                 "--out", str(tmp_path / "o"), "--scheduler", address, "--connect-timeout", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"stereoseed: error: {address}: no Dask scheduler answered within 1 s")
    assert not (tmp_path / "o").exists()


def test_a_workers_address_is_refused_naming_what_answered(scheduler):
    """A Dask worker answers the handshake too: the probe asks what it is before connecting a
    client (which would wait for a scheduler's replies that never come)."""
    worker = sorted(_workers(scheduler))[0]
    t = time.monotonic()
    with pytest.raises(StereoseedError) as caught:
        with executor_for(worker, 2, connect_timeout=5):
            pass
    assert time.monotonic() - t < 5
    assert str(caught.value) == (f"{worker}: that is a Dask Worker, not the scheduler; give the scheduler's address "
                                 f"(dask scheduler prints it), tcp://HOST:PORT")


class _Touch:
    """Unpickled, it creates the file at ``path``: what a hostile peer's pickle could do."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


def _dask_message(message: dict, *frames: bytes) -> bytes:
    """``message`` and extra ``frames`` in Dask's TCP framing (distributed.comm.tcp)."""
    import struct

    import msgpack

    frames = (msgpack.packb(message, use_bin_type=True), *frames)
    prelude = struct.pack(f"Q{len(frames)}Q", len(frames), *map(len, frames))
    return struct.pack("Q", len(prelude) + sum(map(len, frames))) + prelude + b"".join(frames)


@contextmanager
def _hostile_listener(payload: bytes):
    """A listener on 127.0.0.1 that answers every connection, and everything sent on it, with
    ``payload``; yields its address."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.2)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except socket.timeout:
                continue
            with conn:
                conn.settimeout(2)
                try:
                    for _ in range(3):  # the handshake, the question, one more
                        conn.sendall(payload)
                        if not conn.recv(65536):
                            break
                except OSError:
                    pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    finally:
        stop.set()
        thread.join(5)
        server.close()


def test_a_pickle_from_the_scheduler_address_is_never_unpickled(tmp_path, capsys):
    """Issue 48 row 1: whatever answers at --scheduler with a pickle (marked as Dask marks one,
    in the handshake itself) runs nothing: refused in one line before Dask's client reads it."""
    import msgpack
    import pickle

    planted = tmp_path / "planted"
    pickled = msgpack.packb({"pickled-obj": pickle.dumps(_Touch(planted)), "num-sub-frames": 0})
    payload = _dask_message({"compression": None, "python": [3, 11, 0], "pickle-protocol": 5,
                             "type": {"__Pickled__": 1}, "op": {"__Pickled__": 1}}, pickled)
    with _hostile_listener(payload) as address:
        code = main(["reconstruct", str(tmp_path / "images.txt"), "--calib", str(tmp_path / "calib.json"),
                     "--dense", "--out", str(tmp_path / "o"), "--scheduler", address, "--connect-timeout", "2",
                     "--quiet"])
    err = capsys.readouterr().err
    assert not planted.exists()
    assert code == 2 and one_line_error(err)
    assert err.startswith(f"stereoseed: error: {address}: that is not a Dask scheduler")


def test_the_probe_refuses_a_huge_announced_reply_and_odd_addresses(tmp_path):
    """A peer announcing a message of 2**62 bytes is refused before anything is allocated;
    only tcp:// addresses are probed."""
    import struct

    with _hostile_listener(struct.pack("Q", 2**62)) as address:
        with pytest.raises(StereoseedError, match="that is not a Dask scheduler .it announced a message of"):
            with executor_for(address, 2, connect_timeout=2):
                pass
    for bad, says in (("tls://127.0.0.1:1", "only tcp:// addresses"), ("tcp://127.0.0.1", "tcp://HOST:PORT"),
                      ("tcp://127.0.0.1:99999", "tcp://HOST:PORT")):
        with pytest.raises(StereoseedError, match=re.escape(says)):
            with executor_for(bad, 2, connect_timeout=1):
                pass


def test_scheduler_without_dense_and_without_dask_are_refused(sequence_files, tmp_path, capsys, monkeypatch):
    seq = sequence_files
    args = ["reconstruct", str(seq / "images.txt"), "--calib", str(seq / "calib.json"), "--out", str(tmp_path / "o"),
            "--scheduler", "tcp://127.0.0.1:1"]
    assert main(args) == 2
    assert "add --dense" in capsys.readouterr().err
    monkeypatch.setitem(__import__("sys").modules, "distributed", None)  # as if the extra were not installed
    assert main(args + ["--dense"]) == 2
    assert capsys.readouterr().err == ("stereoseed: error: --scheduler needs the cluster extra: "
                                       "pip install 'stereoseed[cluster]'\n")


def test_sequence_list_format(tmp_path):
    (tmp_path / "lists").mkdir()
    listing = tmp_path / "lists" / "s.txt"
    listing.write_text("# comment line\n"
                       "  imgs/a  calib.json  out/a  # trailing comment\n"
                       "\"my images/b.txt\" /abs/calib.json /abs/out/b\n")
    a, b = read_sequence_list(listing, allow_outside=True)  # /abs/out/b lies outside the list's folder
    base = listing.parent.resolve()
    assert (a.name, a.images, a.calib, a.out, a.line) == ("out/a", str(base / "imgs/a"), str(base / "calib.json"),
                                                          str(base / "out/a"), 2)
    assert (b.images, b.calib, b.out) == (str(base / "my images/b.txt"), "/abs/calib.json", "/abs/out/b")
    assert (read_sequence_list(listing, tmp_path / "root", allow_outside=True)[0].out
            == str((tmp_path / "root" / "out/a").resolve()))
    for text, says in (("a b\n", "line 1: 2 field(s)"), ("a b c\nd e c\n", "lines 1 and 2: both write c"),
                       ("\"a b c\n", "line 1: No closing quotation"), ("# nothing\n", "no sequence"),
                       ("a b c\nd\0 e f\n", "line 2: a NUL byte, which no path can hold")):  # issue 48 row 11
        listing.write_text(text)
        with pytest.raises(StereoseedError, match=re.escape(says)):
            read_sequence_list(listing)


def _slow_then_fast(k: int) -> int:
    time.sleep(0.3 if k == 0 else 0.0)
    return k * k


def test_in_order_hands_back_results_in_job_order():
    """The first job finishes last; the results still come back in job order, through the local
    pool and in this process."""
    with executor_for(None, 2) as pool:
        assert pool.slots == 2 and not pool.remote
        assert [f.result() for f in pool.in_order(_slow_then_fast, range(5))] == [0, 1, 4, 9, 16]
    with executor_for(None, 1) as pool:
        assert [f.result() for f in pool.in_order(_slow_then_fast, range(3))] == [0, 1, 4]
    failed = JobPool().submit(int, "x")
    with pytest.raises(ValueError):
        failed.result()


_BUSY_POOL = """
import sys, time
from stereoseed.cluster import executor_for
with executor_for(None, 2) as pool:
    for _ in range(2):
        pool.submit(time.sleep, 60)
    print("busy", flush=True)
    time.sleep(60)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only; the test reads /proc")
def test_a_local_pools_busy_workers_die_when_their_parent_is_killed():
    """End to end: a command's local pool (executor_for) with a job running in each worker, its
    process alone killed (SIGKILL: nothing of its own runs): the workers go at once, not when
    their 60 s jobs end (a worker of a killed run would otherwise hold its core and memory)."""
    import signal
    import subprocess

    parent = subprocess.Popen([sys.executable, "-c", _BUSY_POOL], start_new_session=True, stdout=subprocess.PIPE,
                              text=True)
    try:
        assert parent.stdout.readline().strip() == "busy"
        assert wait_until(lambda: len(alive_in_group(parent.pid)) == 3, 10.0)  # the parent and its two workers
        time.sleep(0.2)  # the workers take their jobs
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        assert wait_until(lambda: not alive_in_group(parent.pid), 10.0), "a worker outlived its parent"
    finally:
        parent.stdout.close()
        if alive_in_group(parent.pid):
            os.killpg(parent.pid, signal.SIGKILL)


def test_pool_workers_die_with_their_parent():
    """The pool initializer asks the kernel to kill a worker whose parent dies (Linux)."""
    import ctypes
    import multiprocessing
    import os
    import signal
    import sys

    from stereoseed.cluster import die_with_parent

    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux-only")

    def child(q):
        die_with_parent(os.getppid())
        sig = ctypes.c_int(0)
        ctypes.CDLL(None).prctl(2, ctypes.byref(sig), 0, 0, 0)  # PR_GET_PDEATHSIG
        q.put(sig.value)

    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=child, args=(q,))
    p.start()
    assert q.get(timeout=30) == signal.SIGKILL
    p.join()
