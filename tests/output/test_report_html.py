"""report.html: written atomically, self-contained, robust to failed images and missing parts;
drawn in headless Chromium without console errors; `stereoseed view`."""
from __future__ import annotations

import html
import html.parser
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from browser_helpers import CHROMIUM_ARGS, playwright_chromium

from stereoseed.errors import StereoseedError

from stereoseed.output.report import html as report_html
from stereoseed.cli import main
from stereoseed.config import Config
from stereoseed.pipeline import reconstruct
from stereoseed.sfm.correspondence import HarrisZncc
from stereoseed.output.report.html import write_report_html



@pytest.fixture(scope="module")
def run(box_scene):
    """A 6-image synthetic ring with a blank image inserted as the 4th: one image fails."""
    scene = box_scene.prefix(6)
    images, names = list(scene.images), list(scene.names)
    images.insert(3, np.zeros_like(images[0]))
    names.insert(3, "blank.png")
    recon, report = reconstruct(images, names, scene.P[:2], Config())
    return recon, report


@pytest.fixture(scope="module")
def written(run, tmp_path_factory):
    out = tmp_path_factory.mktemp("result")
    path = write_report_html(*run, out, source=HarrisZncc.of(Config()))  # what redraws the weakest insertion
    return path, path.read_text(encoding="utf-8")


class _Rows(html.parser.HTMLParser):
    """The cells of each row of the per-image table's body."""

    def __init__(self):
        super().__init__()
        self.rows: list[list[str]] = []
        self._in_table = self._in_body = self._in_cell = False

    def handle_starttag(self, tag, attrs):
        if tag == "table" and dict(attrs).get("id") == "per-image":
            self._in_table = True
        elif self._in_table and tag == "tbody":
            self._in_body = True
        elif self._in_body and tag == "tr":
            self.rows.append([])
        elif self._in_body and tag == "td":
            self._in_cell = True
            self.rows[-1].append("")

    def handle_endtag(self, tag):
        if tag == "td":
            self._in_cell = False
        elif tag == "tbody":
            self._in_body = False
        elif tag == "table":
            self._in_table = False

    def handle_data(self, data):
        if self._in_cell:
            self.rows[-1][-1] += data


def _table(text: str) -> dict[str, list[str]]:
    parser = _Rows()
    parser.feed(text)
    return {row[1]: row for row in parser.rows}


def test_report_written_with_a_row_per_image(run, written):
    recon, report = run
    path, text = written
    assert path.name == "report.html" and path.is_file()
    rows = _table(text)
    assert list(rows) == [v.name for v in recon.views]
    for r in report["per_image"]:
        assert rows[r["image"]][2] == r["status"]
    assert rows["img_000.png"][2] == "calibrated" and rows["img_001.png"][2] == "calibrated pair"
    assert rows["img_002.png"][2] == "registered"
    # the summary, the 3D view and its frustums, the plots and the match image are there
    assert f"{report['registered']} / {report['images']} images" in text
    for part in ('id="view3d"', 'id="path"', 'id="reprojection"', 'id="times"', "cameras: registered",
                 "Matches of the weakest insertion", 'src="data:image/png;base64,'):
        assert part in text, part


def test_failed_image_reported_with_its_reason(run, written):
    _, report = run
    _, text = written
    failed = [r for r in report["per_image"] if r["status"] == "failed"]
    assert [r["image"] for r in failed] == ["blank.png"]
    row = _table(text)["blank.png"]
    assert row[2] == "failed" and row[3] == failed[0]["reason"] and row[3]
    assert report["registered"] == report["images"] - 1


def test_the_weakest_insertions_panel_draws_a_few_dozen_of_its_matches(written):
    _, text = written
    caption = html.unescape(re.search(r"Matches of the weakest insertion</h2><p class=\"note\">(.*?)</p>", text).group(1))
    drawn, total = map(int, re.search(r"; (\d+) of the (\d+) matches under the known epipolar geometry drawn, "
                                      r"spread over the image", caption).groups())
    assert drawn == report_html.MAX_MATCH_LINES < total


def test_report_is_self_contained(written):
    _, text = written
    tags = re.findall(r"<(?:script|link|img|iframe|source)\b[^>]*>", text, flags=re.I)
    assert tags
    for tag in tags:
        assert not re.search(r"\b(?:src|href)\s*=\s*[\"']?\s*(?:https?:)?//", tag, flags=re.I), tag
    assert not re.search(r"@import\s+url\(\s*[\"']?(?:https?:)?//", text)
    assert text.count("plotly.js v") == 1  # the bundle, inlined once
    assert len(text) < 12e6


def test_write_is_atomic(run, tmp_path, monkeypatch):
    out = tmp_path / "new" / "result"
    path = write_report_html(*run, out)
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]  # no temporary file left
    before = path.read_bytes()

    def failing_write(self, *args, **kwargs):
        Path.write_bytes(self, b"<!DOCTYPE html><html>partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", failing_write)
    with pytest.raises(StereoseedError, match="report.html: cannot write"):  # the user's path, not the temp file
        write_report_html(*run, out)
    assert path.read_bytes() == before  # the old report stays whole
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]


def test_a_failing_part_is_logged_and_left_out(run, tmp_path, monkeypatch, caplog):
    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(report_html, "_weakest_insertion", broken)
    monkeypatch.setattr(report_html, "figure_times", broken)
    with caplog.at_level(logging.WARNING, logger="stereoseed.output.report.html"):
        text = write_report_html(*run, tmp_path, source=HarrisZncc.of(Config())).read_text(encoding="utf-8")
    assert "Matches of the weakest insertion" not in text and 'id="times"' not in text
    assert 'id="view3d"' in text and "blank.png" in text
    assert any("weakest insertion" in r.getMessage() and "boom" in r.getMessage() for r in caplog.records)


def test_report_with_missing_keys_and_no_source(run, tmp_path):
    """An empty report dict, no correspondence source to match with, no dense cloud."""
    recon, _ = run
    text = write_report_html(recon, {}, tmp_path).read_text(encoding="utf-8")
    assert 'id="view3d"' in text and "Matches of the weakest insertion" not in text


def test_view_prints_the_uri(written, capsys):
    path, _ = written
    assert main(["view", str(path.parent), "--print"]) == 0
    assert capsys.readouterr().out.strip() == path.resolve().as_uri()


def test_view_opens_the_browser(written, capsys, monkeypatch):
    import webbrowser

    path, _ = written
    opened = []
    monkeypatch.setattr(webbrowser, "open", lambda uri: opened.append(uri) or True)
    assert main(["view", str(path.parent)]) == 0
    assert opened == [path.resolve().as_uri()]


def test_view_without_report_is_a_one_line_error(tmp_path, capsys):
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == f"stereoseed: error: {tmp_path}: no report.html; run stereoseed reconstruct --out {tmp_path} first\n"


# ---------------------------------------------------------------- in a real browser


def test_report_renders_in_headless_chromium(written, tmp_path):
    import cv2

    sync_playwright, chromium = playwright_chromium()
    path, _ = written
    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS,
                                    env={"HOME": str(tmp_path)})
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            page.on("request", lambda r: problems.append(f"request: {r.url}") if not r.url.startswith(("file:", "data:", "blob:")) else None)
            page.goto(path.resolve().as_uri())
            page.wait_for_selector("body[data-rendered]", timeout=20_000)
            page.wait_for_selector("#view3d canvas", timeout=10_000)
            page.wait_for_timeout(500)
            for plot in ("view3d", "path", "reprojection", "times"):
                assert page.locator(f"#{plot} .main-svg").count() > 0, plot  # Plotly drew it
            shot = tmp_path / "report.png"
            page.screenshot(path=str(shot), full_page=True)
            view = page.locator("#view3d").screenshot(path=str(tmp_path / "view3d.png"))
        finally:
            browser.close()
    assert not problems, problems
    assert shot.stat().st_size > 0
    img = cv2.imdecode(np.frombuffer(view, np.uint8), cv2.IMREAD_COLOR).astype(int)
    background = np.array([0x30, 0x24, 0x1F])  # the 3D view's background, BGR
    drawn = np.any(np.abs(img - background) > 40, axis=2)
    assert drawn.mean() > 0.002, "the WebGL canvas drew nothing"
    red = (img[..., 2] > 150) & (img[..., 1] < 90) & (img[..., 0] < 90)  # the frustums (#d62728)
    assert red.sum() > 50, "no camera frustum drawn"


def test_far_outliers_do_not_shrink_the_3d_view(run, monkeypatch):
    """A stray point far along a ray is left out of the drawn clouds (and counted), so the scene
    does not shrink to a dot."""
    import json

    recon, report = run
    pts, cols = recon.live_points()
    far = np.vstack([pts, [[0.0, 0.0, -100.0]]])
    monkeypatch.setattr(recon, "live_points", lambda: (far, np.vstack([cols, [[255, 0, 0]]])))
    text = report_html.render_report_html(recon, report)
    figures = json.loads(re.search(r'<script type="application/json" id="figures">(.*?)</script>', text, re.S).group(1))
    sparse = next(t for t in figures["view3d"]["data"] if t["name"].startswith("sparse"))
    assert sparse["name"] == f"sparse ({len(far)} points; 1 far outlier not shown)"
    assert len(sparse["z"]) == len(pts) and min(sparse["z"]) > -10


def test_the_dense_cloud_given_is_drawn_and_counted(run):
    import json

    from stereoseed.dense.densify import DenseCloud

    recon, report = run
    pts, cols = recon.live_points()
    cloud = DenseCloud(pts + 0.001, cols, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), np.ones(len(pts), np.int64))
    text = report_html.render_report_html(recon, {k: v for k, v in report.items() if k != "dense"}, dense=cloud)
    figures = json.loads(re.search(r'<script type="application/json" id="figures">(.*?)</script>', text, re.S).group(1))
    dense = next(t for t in figures["view3d"]["data"] if t["name"].startswith("dense"))
    assert dense["name"].startswith(f"dense ({len(pts)} of {len(pts)} points")
    assert f"<span>dense points</span><b>{len(pts)}</b>" in text  # the summary counts it
    without = report_html.render_report_html(recon, report)
    assert not any(t["name"].startswith("dense") for t in json.loads(re.search(
        r'<script type="application/json" id="figures">(.*?)</script>', without, re.S).group(1))["view3d"]["data"])


def _rects_overlap(a: dict, b: dict) -> bool:
    return a["x"] < b["x"] + b["width"] and b["x"] < a["x"] + a["width"] and \
        a["y"] < b["y"] + b["height"] and b["y"] < a["y"] + a["height"]


@pytest.mark.slow  # a browser, and the mouse moved over the view until it is over two points
def test_the_scale_bar_the_distance_readout_and_the_toolbars_in_chromium(run, tmp_path):
    """In a real browser: the scale bar is drawn (its yellow goes when it is hidden); two clicks
    on points of the sparse cloud give their distance in the model's unit; Plotly's toolbar,
    shown as the mouse is over a plot, covers none of its legend."""
    import json

    import cv2

    from stereoseed.output.report.measure import length_text

    sync_playwright, chromium = playwright_chromium()
    recon, report = run
    path = write_report_html(recon, {**report, "unit": "m"}, tmp_path)  # the synthetic box is in metres
    figures = json.loads(re.search(r'<script type="application/json" id="figures">(.*?)</script>',
                                   path.read_text(encoding="utf-8"), re.S).group(1))
    names = [t["name"] for t in figures["view3d"]["data"]]
    sparse = next(t for t in figures["view3d"]["data"] if t["name"].startswith("sparse"))
    cloud = np.column_stack([sparse["x"], sparse["y"], sparse["z"]])
    problems: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS, env={"HOME": str(tmp_path)})
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            page.goto(path.resolve().as_uri())
            page.wait_for_selector("body[data-rendered]", timeout=20_000)
            page.wait_for_selector("#view3d canvas", timeout=10_000)
            page.wait_for_timeout(500)
            # the toolbars beside the legends
            for plot in ("view3d", "reprojection", "times"):
                page.locator(f"#{plot}").scroll_into_view_if_needed()
                page.locator(f"#{plot}").hover(position={"x": 60, "y": 120})
                page.wait_for_timeout(200)
                toolbar = page.locator(f"#{plot} .modebar").bounding_box()
                legend = page.locator(f"#{plot} .legend").bounding_box()
                assert toolbar and toolbar["width"] > 50 and legend and legend["width"] > 20, plot
                assert not _rects_overlap(toolbar, legend), (plot, toolbar, legend)
            # the scale bar: its yellow is drawn, and goes when the bar is hidden
            page.locator("#view3d").scroll_into_view_if_needed()
            page.mouse.move(0, 0)
            page.wait_for_timeout(200)

            def yellow() -> tuple[np.ndarray, int]:
                shot = cv2.imdecode(np.frombuffer(page.locator("#view3d").screenshot(), np.uint8), cv2.IMREAD_COLOR)
                bgr = shot.astype(int)
                return shot, int(np.sum(np.all(np.abs(bgr - [0x4F, 0xD5, 0xFF]) < 40, axis=2)))

            shot, with_bar = yellow()
            bar = names.index(next(n for n in names if n.startswith("scale bar")))
            page.evaluate(f"() => Plotly.restyle('view3d', {{visible: false}}, [{bar}])")
            page.wait_for_timeout(300)
            _, without_bar = yellow()
            page.evaluate(f"() => Plotly.restyle('view3d', {{visible: true}}, [{bar}])")
            page.wait_for_timeout(300)
            assert with_bar > 60 and without_bar < with_bar / 5, (with_bar, without_bar)
            # two points of the sparse cloud, found where the mouse over the view picks them
            page.evaluate("""() => { window.hovered = null; document.getElementById('view3d').on('plotly_hover',
                function(e){ var q = e.points[0]; window.hovered = {c: q.curveNumber, x: q.x, y: q.y, z: q.z}; }); }""")
            box = page.locator("#view3d").bounding_box()
            background = np.array([0x30, 0x24, 0x1F])
            lit = np.argwhere(np.abs(shot.astype(int) - background).sum(axis=2) > 120)
            found = []
            for k in np.random.default_rng(0).permutation(len(lit))[:300]:
                y, x = map(float, lit[k])
                page.evaluate("() => { window.hovered = null; }")
                page.mouse.move(box["x"] + x, box["y"] + y)
                page.wait_for_timeout(40)
                hit = page.evaluate("() => window.hovered")
                if hit and names[hit["c"]].startswith("sparse") and all(
                        np.hypot(x - fx, y - fy) > 40 for fx, fy, _ in found):
                    found.append((x, y, hit))
                    if len(found) == 2:
                        break
            assert len(found) == 2, "no two points of the sparse cloud under the mouse"
            for x, y, _ in found:  # a click: the button held while Plotly draws a frame
                page.mouse.move(box["x"] + x, box["y"] + y)
                page.wait_for_timeout(100)
                page.mouse.down()
                page.wait_for_timeout(150)
                page.mouse.up()
                page.wait_for_timeout(150)
            readout = page.locator("#distance")
            text, distance = readout.text_content(), float(readout.get_attribute("data-distance"))
            picked = np.array(json.loads(readout.get_attribute("data-points")))
            drawn = page.evaluate(f"() => {{ var t = document.getElementById('view3d').data[{len(names) - 1}]; "
                                  f"return [t.x, t.y, t.z]; }}")
        finally:
            browser.close()
    assert not problems, problems
    expected = np.array([[h["x"], h["y"], h["z"]] for _, _, h in found])
    assert np.allclose(picked, expected, atol=1e-12)  # the points clicked, ...
    assert all(np.min(np.abs(cloud - q).max(axis=1)) < 1e-9 for q in picked)  # ... points of the cloud
    assert distance == pytest.approx(float(np.linalg.norm(expected[1] - expected[0])), rel=1e-12)
    assert text.startswith(f"distance: {length_text(distance, 'm')} between ("), text
    assert np.allclose(np.array(drawn).T, expected)  # the measured segment drawn in the view


def test_the_summary_says_the_model_used_the_points_written_and_the_unit(run, tmp_path):
    """No image zoomed: the header names the fixed model the rows show, not only the one asked
    for; the sparse points are those written (far ones left out, counted); a named unit shows."""
    recon, report = run
    report = dict(report, final=dict(report["final"], no_zoom=True), camera_model="focal", unit="m",
                  exported_points=report["points"] - 1, far_points_dropped=1)
    text = write_report_html(recon, report, tmp_path).read_text(encoding="utf-8")
    assert "<b>fixed: no image zoomed (focal asked)</b>" in text
    assert f"<b>{report['points'] - 1} (1 far left out)</b>" in text and "<span>unit</span><b>m</b>" in text
