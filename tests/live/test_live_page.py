"""The live page in headless Chromium while photos arrive: the camera count grows, a skipped
photo shows its reason; a file still being written, an unreadable one, a deleted one and a
browser that leaves each get a line in the page and the log, and nothing is lost."""
from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from browser_helpers import CHROMIUM_ARGS, playwright_chromium

from cli_helpers import cli_command, one_line_error, run as run_cli
from scene_helpers import scene_on_disk
from stereoseed.live import LiveConfig, LivePage, run_live

FAST = LiveConfig(poll_s=0.05, stable_s=0.1, unreadable_after_s=0.4, heartbeat_s=0.3)


@pytest.fixture(scope="module")
def photos(tmp_path_factory, small_box_scene):
    """Four photos of the small ring (paths in order) and calib.json."""
    folder = tmp_path_factory.mktemp("photos")
    paths, calib = scene_on_disk(small_box_scene.prefix(4), folder, images=folder / "src")
    return list(paths["images"]), calib




def _put(path: Path, folder: Path, name: str | None = None) -> Path:
    """A photo arriving whole, as a sync tool puts it: written beside, then renamed in."""
    target = folder / (name or path.name)
    tmp = folder / f".{target.name}.tmp"
    shutil.copyfile(path, tmp)
    os.replace(tmp, target)
    return target


def _live(watch: Path, calib: Path, out: Path, **kw):
    """run_live in a thread: (thread, stop event, the page's URL, {"report" or "error"})."""
    stop, started, result = threading.Event(), threading.Event(), {}
    url = []

    def target():
        try:
            result["report"] = run_live(watch, calib, out, live=FAST, port=0, stop=stop,
                                        on_start=lambda u: (url.append(u), started.set()), **kw)
        except BaseException as e:  # noqa: BLE001 - handed to the test
            result["error"] = e
            started.set()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    assert started.wait(30) and "error" not in result, result
    return thread, stop, url[0], result


def test_the_page_grows_while_photos_arrive_and_says_what_went_wrong(photos, tmp_path, caplog):
    sync_playwright, chromium = playwright_chromium()
    paths, calib = photos
    watch = tmp_path / "watch"
    watch.mkdir()
    caplog.set_level(logging.INFO, logger="stereoseed.live")
    thread, stop, url, result = _live(watch, calib, tmp_path / "result")
    problems, counts = [], []
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS, env={"HOME": str(tmp_path)})
            try:
                page = browser.new_page(viewport={"width": 1200, "height": 900})
                page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
                page.on("request", lambda r: problems.append(f"request: {r.url}") if not r.url.startswith(url) else None)
                page.goto(url)

                def photos_shown(n):
                    page.wait_for_function(f"Number(document.getElementById('count-photos').textContent) >= {n}",
                                           timeout=20_000)
                    counts.append(int(page.locator("#count-cameras").text_content()))

                for k, path in enumerate(paths[:3]):
                    _put(path, watch)
                    photos_shown(k + 1)
                page.wait_for_selector("#view3d canvas", timeout=10_000)  # the 3D view, drawn
                assert page.locator("#last-photo").get_attribute("src").startswith("data:image/jpeg;base64,")
                # a photo still being written: taken once whole
                partial = watch / paths[3].name
                data = paths[3].read_bytes()
                partial.write_bytes(data[: len(data) // 2])
                time.sleep(0.3)
                partial.write_bytes(data)
                photos_shown(4)
                # one that never decodes: taken after the wait, skipped with the reader's reason
                (watch / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 300)
                photos_shown(5)
                row = page.locator('tr[data-image="broken.png"]')
                assert "failed" in row.get_attribute("class")
                reason = row.locator("td").nth(2).text_content()
                assert "not a readable image" in reason and reason in page.locator("#last").text_content()
                hints = page.locator("#hints").text_content()
                assert f"Move back towards the last good view, {paths[3].name}" in hints and "in a row" not in hints
                (watch / paths[0].name).unlink()  # deleted after it was taken: the run keeps its copy
                page.wait_for_function("document.getElementById('events').textContent.includes('after it was taken')",
                                       timeout=10_000)
                log_text = page.locator("#events").text_content()
                hints = page.locator("#hints").text_content()
            finally:
                browser.close()
    finally:
        stop.set()
        thread.join(60)
    assert not problems, problems
    assert "error" not in result, result
    assert counts[0] == 0 and counts[1] == 2 and counts[2] == 3 and counts[-1] > counts[2]  # the cameras, growing
    for said in ("still being written", "not decodable yet", "broken.png: skipped: ", "deleted from"):
        assert said in log_text, said
        assert said in caplog.text, said
    assert hints
    # nothing lost: every photo is in the result, the broken one with its reason
    cameras = {c["name"]: c for c in json.loads((tmp_path / "result" / "cameras.json").read_text())["images"]}
    assert list(cameras) == [p.name for p in paths[:4]] + ["broken.png"]
    report = result["report"]
    broken = next(r for r in report["per_image"] if r["image"] == "broken.png")
    assert broken["status"] == "failed" and "not a readable image" in broken["reason"]
    assert (tmp_path / "result" / "images" / paths[0].name).read_bytes() == paths[0].read_bytes()


def _events(url: str) -> list[str]:
    with urllib.request.urlopen(url + "state", timeout=5) as r:
        return [e["line"] for e in json.loads(r.read())["events"]]


def test_a_browser_that_leaves_is_said_and_the_others_miss_nothing():
    with LivePage(0, FAST) as page:
        assert page.url.startswith("http://127.0.0.1:")
        page.publish({"photos": 1})
        page.event("first line")
        sock = socket.create_connection(("127.0.0.1", page.port), timeout=5)
        sock.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        got = b""
        while b"first line" not in got:  # the headers, then the state
            chunk = sock.recv(65536)
            assert chunk, got
            got += chunk
        sock.close()  # the browser goes away
        deadline = time.monotonic() + 10
        while not any("disconnected" in line for line in _events(page.url)) and time.monotonic() < deadline:
            time.sleep(0.05)
        lines = _events(page.url)
        assert lines[0] == "first line" and "a browser disconnected" in lines[1]
        with urllib.request.urlopen(page.url + "events", timeout=5) as r:  # a browser that comes back: all of it
            first = r.readline() + r.readline()
        assert b"first line" in first and b"disconnected" in first
        with urllib.request.urlopen(page.url + "plotly.js", timeout=5) as r:  # served here: works offline
            assert len(r.read()) > 1_000_000


def test_the_command_stops_after_n_photos_and_refuses_bad_input(photos, tmp_path, capsys):
    paths, calib = photos
    watch = tmp_path / "watch"
    watch.mkdir()
    for p in paths[:3]:
        _put(p, watch)
    code, out, err = run_cli(capsys, "live", "--watch", watch, "--calib", calib, "--out", tmp_path / "r",
                             "--until", 3, "--port", 0, "--quiet")
    assert code == 0, err
    assert "live page: http://127.0.0.1:" in out and "3/3 photos placed" in out
    assert (tmp_path / "r" / "cameras.json").is_file()
    code, out, err = run_cli(capsys, "live", "--watch", tmp_path / "nowhere", "--calib", calib, "--out",
                             tmp_path / "r2")
    assert code == 2 and one_line_error(err) and "not a folder" in err
    assert not (tmp_path / ".r2.partial").exists()


def test_ctrl_c_stops_the_command_and_writes_the_result_with_its_dense_cloud(photos, tmp_path):
    import signal
    import subprocess

    paths, calib = photos
    watch = tmp_path / "watch"
    watch.mkdir()
    for p in paths[:3]:
        _put(p, watch)
    log = tmp_path / "out.txt"
    with open(log, "w") as out:
        proc = subprocess.Popen(cli_command("live", "--watch", watch, "--calib", calib, "--out", tmp_path / "r",
                                            "--port", 0, "--dense"), stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while paths[2].name + ": registered" not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(60)
        except subprocess.TimeoutExpired:
            pytest.fail("no exit within 60 s of Ctrl-C; its output:\n" + log.read_text())
        assert code == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert "stopping (Ctrl-C" in text and "3/3 photos placed" in text and "Traceback" not in text
    assert (tmp_path / "r" / "cameras.json").is_file() and not (tmp_path / ".r.partial").exists()
    assert (tmp_path / "r" / "dense.ply").stat().st_size > 1000  # --dense: the dense stage once stopped


def test_the_log_keeps_its_last_lines_and_the_state_is_sent_as_published():
    from dataclasses import replace

    with LivePage(0, replace(FAST, log_lines=3)) as page:
        page.publish({"photos": 2, "names": ["a.jpg", "b.jpg"]})
        for k in range(5):
            page.event(f"line {k}")
        version, body = page.message()
        got = json.loads(body)
        assert got["version"] == version == 6
        assert got["state"] == {"photos": 2, "names": ["a.jpg", "b.jpg"]}
        assert [e["line"] for e in got["events"]] == ["line 2", "line 3", "line 4"]
    with pytest.raises(ValueError, match="log_lines"):
        LiveConfig(log_lines=0)
