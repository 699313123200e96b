"""Faults of the processes that run the jobs, with real processes: a local pool's worker killed
(as the OOM killer does) mid-job or while it sends its result, a command interrupted while a
worker does not answer, and a --scheduler address where something other than a Dask scheduler
listens. Each must end in bounded time: a redone job and the right results, or one line."""
import http.server
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from process_helpers import alive_in_group, children, wait_until
from cli_helpers import cli_command
from scene_helpers import scene_on_disk
from stereoseed.cli import main
from stereoseed.cluster import executor_for
from stereoseed.errors import StereoseedError
from stereoseed.io.ply import read_ply_vertices

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the tests kill processes, read /proc")

LIMIT_S = 60  # no test may hang: past this the test fails (it takes seconds)


@pytest.fixture(autouse=True)
def bounded():
    """Fail a test still running after LIMIT_S (SIGALRM raises in the main thread, where a hung
    wait on a job's result or a handshake sits)."""
    def expire(signum, frame):
        raise TimeoutError(f"still running after {LIMIT_S} s")

    before = signal.signal(signal.SIGALRM, expire)
    signal.alarm(LIMIT_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)


@pytest.fixture(scope="module")
def ring(tmp_path_factory, small_box_scene):
    """The 14-image ring of 320x240 images on disk: 13 pairs for the dense stage (about a second
    on two workers). Returns (images.txt, calib.json)."""
    paths, calib = scene_on_disk(small_box_scene, tmp_path_factory.mktemp("ring"))
    return paths["images_txt"], calib


# --- a local pool's worker killed -------------------------------------------------------------
def _dies_once(job: tuple) -> int:
    """k * k; but the first time it is run with ``dies``, its worker SIGKILLs itself (once: a
    marker file says it happened)."""
    k, dies, marker = job
    if dies and not os.path.exists(marker):
        Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return k * k


def _always_dies(k: int) -> int:
    """k, after 0.2 s (the jobs after it are still in the pool when it dies); job 2 SIGKILLs its
    worker instead, every time."""
    if k == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.2)
    return k


def test_a_job_whose_worker_is_killed_is_run_again_and_the_results_are_right(tmp_path, caplog):
    before = children(os.getpid())
    jobs = [(k, k in (2, 5), str(tmp_path / f"died{k}")) for k in range(8)]
    t = time.monotonic()
    with caplog.at_level("WARNING", logger="stereoseed"), executor_for(None, 2) as pool:
        results = [f.result() for f in pool.in_order(_dies_once, jobs)]
    took = time.monotonic() - t
    assert results == [k * k for k in range(8)]
    assert (tmp_path / "died2").exists() and (tmp_path / "died5").exists()  # both did die once
    # one warning a broken pool: the two deaths may fall in the same one
    deaths = [r.getMessage() for r in caplog.records if "a worker process died" in r.getMessage()]
    assert 1 <= len(deaths) <= 2
    assert all(d.startswith("a worker process died (killed by signal 9 (SIGKILL): out of memory?); running the ")
               for d in deaths)
    assert took < 15, f"{took:.1f} s"  # measured 0.4 s
    assert wait_until(lambda: children(os.getpid()) <= before, 5.0), "a worker outlived its pool"


def test_a_job_that_kills_its_worker_again_fails_with_one_line_and_the_others_go_on():
    """Every job is in the pool when the first death breaks it, and in the fresh pool when the
    second does: only the job whose worker died both times fails, the others run to the end."""
    before = children(os.getpid())
    t = time.monotonic()
    with executor_for(None, 2) as pool:
        futures = [pool.submit(_always_dies, k) for k in range(6)]
        errors = [f.exception(timeout=30) for f in futures]
        results = {k: f.result() for k, f in enumerate(futures) if errors[k] is None}
    took = time.monotonic() - t
    assert results == {k: k for k in range(6) if k != 2}
    assert isinstance(errors[2], StereoseedError)
    message = str(errors[2])
    assert "\n" not in message
    assert message.startswith("a worker process died (killed by signal 9 (SIGKILL): out of memory?) while running "
                              "job 3 (_always_dies), for the second time; ")
    assert "fewer worker processes" in message
    assert took < 15, f"{took:.1f} s"  # measured 1.4 s
    assert wait_until(lambda: children(os.getpid()) <= before, 5.0), "a worker outlived its pool"


def test_a_pool_that_cannot_be_started_again_fails_its_jobs_with_one_line(tmp_path, monkeypatch):
    """After a death the fresh pool's fork is refused (as it may be when memory ran out): the
    jobs fail at once instead of waiting for a pool that will not come."""
    from stereoseed import cluster

    first_start = cluster._LocalPool._start
    starts = []

    def start_once(self):
        starts.append(self.workers)
        if len(starts) > 1:
            raise OSError(12, "Cannot allocate memory")
        first_start(self)

    monkeypatch.setattr(cluster._LocalPool, "_start", start_once)
    jobs = [(k, k == 1, str(tmp_path / f"died{k}")) for k in range(4)]
    t = time.monotonic()
    with pytest.raises(StereoseedError) as caught, executor_for(None, 2) as pool:
        for f in pool.in_order(_dies_once, jobs):
            f.result()
    assert time.monotonic() - t < 15
    assert starts == [2, 1]
    assert str(caught.value) == ("a worker process died and no fresh one could be started ([Errno 12] Cannot "
                                 "allocate memory); free memory, or run with fewer worker processes "
                                 "(DenseConfig.workers)")


# the job's thread blocked in write(2) sending its 16 MB result, which the pool's manager thread
# has begun to read: killed then, the worker leaves the reader waiting for the rest, forever
# unless the pool looks at its workers itself (the executor does not). A script of its own:
# a pool that hangs would also hang the interpreter's exit.
_WRITE = {"x86_64": 1, "aarch64": 64}.get(os.uname().machine)
_KILLED_SENDING = textwrap.dedent("""
    import os, signal, sys, threading, time
    import numpy as np
    from stereoseed.cluster import executor_for

    MARKER = sys.argv[1]

    def job(k):
        result = np.full(2_000_000, float(k))
        if k == 1 and not os.path.exists(MARKER):
            open(MARKER, "w").close()
            tid = threading.get_native_id()

            def kill_while_sending():
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline:
                    with open(f"/proc/self/task/{tid}/syscall") as f:
                        if f.read().split()[0] == "WRITE":
                            break
                    time.sleep(0.0005)
                time.sleep(0.01)
                os.kill(os.getpid(), signal.SIGKILL)

            threading.Thread(target=kill_while_sending, daemon=True).start()
        return result

    with executor_for(None, 2) as pool:
        print([float(f.result()[-1]) for f in pool.in_order(job, range(6))], flush=True)
""")


@pytest.mark.skipif(_WRITE is None, reason="the script knows write(2)'s number on x86_64 and aarch64 only")
def test_a_worker_killed_while_sending_its_result_does_not_hang_the_run(tmp_path):
    script = _KILLED_SENDING.replace('"WRITE"', f'"{_WRITE}"')
    t = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "died")], start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("the run hung after its worker was killed while sending its result")
    took = time.monotonic() - t
    assert proc.returncode == 0, err
    assert out.strip() == str([float(k) for k in range(6)])
    assert (tmp_path / "died").exists()
    assert "a worker process died (killed by signal 9 (SIGKILL): out of memory?); running the " in err
    assert took < 20, f"{took:.1f} s"  # measured 0.7 s, the interpreter's start included
    print(f"killed while sending, whole script: {took:.2f} s")


# --- the command's dense stage ----------------------------------------------------------------
def _first_worker(proc: subprocess.Popen) -> int | None:
    """A pool worker of the command once its dense stage has started one, None if the command
    ended first. The workers are forked (their command line is the command's); multiprocessing's
    resource tracker is forked too but then runs another command line, so a child counts when it
    still has the command's line 50 ms after it was first seen."""
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline:
        forked = [pid for pid in children(proc.pid) if _cmdline(pid) == _cmdline(proc.pid)]
        if forked:
            time.sleep(0.05)
            workers = [pid for pid in forked if _cmdline(pid) == _cmdline(proc.pid)]
            if workers:
                return min(workers)
        time.sleep(0.01)
    return None


def _cmdline(pid: int) -> bytes | None:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes() or None
    except OSError:
        return None


def test_reconstruct_dense_survives_a_killed_worker_with_the_same_cloud(ring, tmp_path):
    """The OOM killer's pick, as a user saw it: one dense worker SIGKILLed mid-stage. The lost
    pairs are redone and the cloud is the one of an undisturbed run."""
    images, calib = ring
    proc = subprocess.Popen(cli_command("reconstruct", images, "--calib", calib, "--dense", "--out", tmp_path / "killed"),
                            start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        worker = _first_worker(proc)
        assert worker is not None, "the command ended before its dense stage started a worker"
        os.kill(worker, signal.SIGKILL)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err
    assert "stereoseed: WARNING: a worker process died (killed by signal 9 (SIGKILL): out of memory?)" in err
    assert "Traceback" not in err
    assert wait_until(lambda: not alive_in_group(proc.pid), 5.0), "a dense worker outlived the command"
    # the reference afterwards: both runs use the kernels Numba cached (a fresh compile of the
    # fastmath alignment kernel differs in the last digits)
    subprocess.run(cli_command("reconstruct", images, "--calib", calib, "--dense", "--out", tmp_path / "whole", "--quiet"),
                   check=True, capture_output=True, timeout=60)
    killed, whole = (read_ply_vertices(tmp_path / name / "dense.ply") for name in ("killed", "whole"))
    assert len(killed) > 100_000  # measured 220,196
    np.testing.assert_array_equal(killed, whole)


def test_sigterm_ends_the_dense_stage_within_seconds_while_a_worker_does_not_answer(ring, tmp_path):
    """A worker stopped (SIGSTOP: it holds its pair and never answers) and then SIGTERM, as a
    user's kill or a batch system's: the command says it was interrupted and ends, leaving no
    worker behind, instead of waiting for a result that will not come."""
    images, calib = ring
    proc = subprocess.Popen(cli_command("reconstruct", images, "--calib", calib, "--dense", "--out", tmp_path / "o",
                                 "--quiet"),
                            start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        worker = _first_worker(proc)
        assert worker is not None, "the command ended before its dense stage started a worker"
        os.kill(worker, signal.SIGSTOP)
        time.sleep(0.3)  # the other worker goes on; the stage waits on the stopped one's pair
        t = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            pytest.fail("SIGTERM did not end the command within 15 s")
        took = time.monotonic() - t
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "stereoseed: interrupted; run the same command with --resume to continue"
    assert "Traceback" not in err
    assert took < 6, f"{took:.1f} s"  # measured 1.3 s: 1 s of grace for the stopped worker, then SIGKILL
    print(f"SIGTERM to exit: {took:.2f} s")
    assert wait_until(lambda: not alive_in_group(proc.pid), 5.0), "a dense worker outlived the command"


# --- --scheduler at an address where no Dask scheduler listens ----------------------------------
@pytest.fixture
def silent_port():
    """A TCP port that accepts connections and never says a word."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept():
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except OSError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield server.getsockname()[1]
    stop.set()
    thread.join()
    for s in held + [server]:
        s.close()


@pytest.fixture
def http_port():
    """A small HTTP server (it answers Dask's handshake bytes with 400 Bad Request)."""
    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()


@pytest.mark.parametrize("listener", ["silent_port", "http_port"])
def test_a_scheduler_address_where_something_else_listens_fails_within_the_connect_timeout(listener, request, ring,
                                                                                           tmp_path, capsys):
    address = f"tcp://127.0.0.1:{request.getfixturevalue(listener)}"
    images, calib = ring
    t = time.monotonic()
    code = main(["reconstruct", str(images), "--calib", str(calib), "--dense", "--out", str(tmp_path / "o"),
                 "--scheduler", address, "--connect-timeout", "2", "--quiet"])
    took = time.monotonic() - t
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"stereoseed: error: {address}: no Dask scheduler answered within 2 s (")
    assert err.rstrip().endswith("tcp://HOST:PORT")
    assert took < 2 + 3, f"{took:.1f} s"  # measured 2.5-2.9 s
    print(f"{listener}: refused after {took:.2f} s")
    assert not (tmp_path / "o").exists()


def test_a_job_the_dask_cluster_gave_up_is_one_line():
    import types

    distributed = pytest.importorskip("distributed")
    from stereoseed.cluster import _OnCluster
    from stereoseed.errors import StereoseedError

    class GivenUp:  # a Dask future whose job killed its worker each time it ran
        def result(self):
            raise distributed.KilledWorker("_run_pair-3", types.SimpleNamespace(address="tcp://127.0.0.1:1"), 3)

    with pytest.raises(StereoseedError, match="gave a job up") as e:
        _OnCluster(GivenUp(), "tcp://10.0.0.1:8786").result()
    assert "\n" not in str(e.value) and "tcp://10.0.0.1:8786" in str(e.value)
