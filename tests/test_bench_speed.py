"""The speed benchmark's process timer (benchmarks/bench_speed.py): what it reports is the
command's own."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_speed import median_run, timed_process  # noqa: E402


def test_peak_memory_is_the_command_s_own_not_the_benchmark_s():
    held = np.ones(40_000_000)  # 320 MB resident in the benchmark's process
    small = timed_process([sys.executable, "-c", "pass"])
    big = timed_process([sys.executable, "-c", "import numpy as np; a = np.ones(25_000_000); a.sum()"])
    assert held.sum() > 0 and small["returncode"] == 0 and big["returncode"] == 0
    assert small["peak_rss_mb"] < 100  # a bare interpreter, not the 320 MB held here
    assert 200 <= big["peak_rss_mb"] < 320 + 100  # its own 200 MB array
    assert 0 < small["seconds"] < big["seconds"] + 60


def test_a_failing_loud_command_gives_its_code_and_last_error_line_without_hanging():
    loud = ("import sys; sys.stderr.write('x' * 500_000 + '\\nthe reason\\n'); print('y' * 500_000); "
            "sys.exit(3)")
    out = timed_process([sys.executable, "-c", loud])
    assert out["returncode"] == 3 and out["stderr"] == ["the reason"]


def test_a_command_killed_by_a_signal_is_told_from_one_that_exits_with_a_code():
    killed = timed_process([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])
    exited = timed_process([sys.executable, "-c", "import sys; sys.exit(137)"])
    assert killed["returncode"] == -9 and exited["returncode"] == 137


def test_the_warm_figure_is_the_median_run_with_every_run_s_time():
    runs = [{"seconds": 5.5, "stages": "a"}, {"seconds": 4.3, "stages": "b"}, {"seconds": 4.6, "stages": "c"}]
    assert median_run(runs) == {"seconds": 4.6, "stages": "c", "all_seconds": [5.5, 4.3, 4.6]}
