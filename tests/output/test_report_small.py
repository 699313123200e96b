"""report.html's small things (issue #37 item 6): titled by the result folder, not its staging
folder; the whole run's wall time beside its stages'; the model's unit from calib.json in the
summary, the tables, the axes and a scale bar of a round length; the match panel a few dozen
lines spread over the image. The browser side (the bar drawn, the distance readout, the
toolbars beside the legends) is in test_report_html.py."""
from __future__ import annotations

import html
import json
import math
import re
import time

import numpy as np
import pytest

from scene_helpers import scene_on_disk
from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_calibration_unit, write_json
from stereoseed.matching.containers import Matches
from stereoseed.output.report.measure import length_text, round_length
from stereoseed.output.visualize import spread_matches
from stereoseed.pipeline import reconstruct_to_folder

ONE_WORKER = Config().replace(dense={"workers": 1})  # the dense stage in this process


@pytest.fixture(scope="module")
def result(tmp_path_factory, small_box_scene):
    """A dense run of 4 images of the small box ring whose calib.json names its unit (the scene
    is in metres): (its folder, report.json, report.html's text, the call's wall time)."""
    folder = tmp_path_factory.mktemp("small")
    paths, calib = scene_on_disk(small_box_scene.prefix(4), folder, images=folder / "images")
    write_json(calib, {**json.loads(calib.read_text()), "unit": "m"})
    out = folder / "box"
    t0 = time.perf_counter()
    reconstruct_to_folder(str(paths["images_txt"]), str(calib), out, ONE_WORKER, dense=True)
    wall = time.perf_counter() - t0
    return out, json.loads((out / "report.json").read_text()), (out / "report.html").read_text(encoding="utf-8"), wall


def figures(text: str) -> dict:
    return json.loads(re.search(r'<script type="application/json" id="figures">(.*?)</script>', text, re.S).group(1))


def summary(text: str) -> dict[str, str]:
    return {html.unescape(k): html.unescape(v)
            for k, v in re.findall(r'<div class="kv"><span>(.*?)</span><b>(.*?)</b></div>', text)}


def test_the_title_and_heading_are_the_result_folders_name(result):
    out, _, text, _ = result
    assert re.search(r"<title>(.*?)</title>", text).group(1) == "box — stereoseed reconstruction"
    assert re.search(r"<h1>(.*?)</h1>", text).group(1) == "box — stereoseed reconstruction"
    page = text.split("<script>")[0]  # the page, not Plotly's bundle (which has a.partial)
    assert ".box.partial" not in text and ".partial" not in page and not (out.parent / ".box.partial").exists()


def test_the_total_time_is_the_whole_runs_and_holds_its_stages(result):
    _, report, text, wall = result
    timing = report["timing"]
    stages = timing["stages_s"]
    assert sorted(stages) == ["dense", "loading", "sparse"] and all(v > 0 for v in stages.values())
    assert sum(stages.values()) <= timing["total_s"] <= wall
    assert stages["sparse"] >= report["seconds"]  # the incremental run is inside its stage
    assert timing["total_s"] > report["seconds"] + report["dense"]["seconds"] * 0.9  # the dense stage counted
    shown = summary(text)
    assert shown["total time"] == f"{timing['total_s']:.1f} s"
    assert shown["stages"] == " · ".join(f"{k} {stages[k]:.1f} s" for k in ("loading", "sparse", "dense"))


def test_the_unit_of_the_calibration_is_shown_wherever_lengths_are(result):
    out, report, text, _ = result
    assert report["unit"] == "m" and json.loads((out / "cameras.json").read_text())["unit"] == "m"
    assert summary(text)["unit"] == "m"
    assert "<th>position σ (m)</th>" in text
    fig = figures(text)
    assert [fig["view3d"]["layout"]["scene"][f"{a}axis"]["title"]["text"] for a in "xyz"] == ["X (m)", "Y (m)", "Z (m)"]
    assert fig["path"]["layout"]["xaxis"]["title"]["text"].endswith("(m)")
    assert fig["view3d"]["measure"]["unit"] == "m" and fig["view3d"]["measure"]["metric"]["cm"] == 0.01


def test_the_scale_bar_is_a_round_length_of_about_a_fifth_of_the_scene(result):
    _, _, text, _ = result
    view = figures(text)["view3d"]
    bar = next(t for t in view["data"] if t["name"].startswith("scale bar"))
    length = bar["meta"]
    ends = np.array([[bar[a][i] for a in "xyz"] for i in (0, 2)])
    assert np.linalg.norm(ends[1] - ends[0]) == pytest.approx(length, rel=1e-9)
    mantissa = length / 10 ** math.floor(math.log10(length))
    assert min(abs(mantissa - m) for m in (1, 2, 5)) < 1e-9  # 1-2-5 series
    scene = [np.array([[v for v in t[a] if v is not None] for a in "xyz"], float) for t in view["data"]
             if t["name"].startswith(("sparse", "cameras:"))]  # the points and the frustums
    extent = np.ptp(np.hstack(scene), axis=1).max()
    assert 0.08 * extent <= length <= 0.5 * extent  # about a fifth, rounded to the 1-2-5 series
    assert bar["name"] == f"scale bar: {length_text(length, 'm')}" and length_text(length, "m") in bar["text"]


def test_lengths_read_in_the_unit_that_suits_them():
    assert length_text(0.05, "m") == "5 cm"
    assert length_text(200.0, "mm") == "20 cm"
    assert length_text(2000.0, "mm") == "2 m"
    assert length_text(1500.0, "m") == "1.5 km"
    assert length_text(0.5, "mm") == "0.5 mm"
    assert length_text(0.1234, "m") == "12.3 cm"
    assert length_text(0.4, "inch") == "0.4 inch"
    assert length_text(0.4, None) == "0.4 units"
    assert [round_length(t) for t in (0.9, 1.6, 3.0, 3.3, 7.0, 7.2, 0.034, 420.0)] == [1, 2, 2, 5, 5, 10, 0.05, 500]


def test_the_unit_is_read_from_calib_json_when_it_names_one(tmp_path):
    calib = tmp_path / "calib.json"
    write_json(calib, {"cameras": [], "unit": " mm "})
    assert read_calibration_unit(calib) == "mm"
    write_json(calib, {"cameras": []})
    assert read_calibration_unit(calib) is None
    (tmp_path / "par.txt").write_text("2\n")
    assert read_calibration_unit(tmp_path / "par.txt") is None and read_calibration_unit(tmp_path) is None
    write_json(calib, {"cameras": [], "unit": 5})
    with pytest.raises(StereoseedError, match=r'calib.json: "unit" is 5; give a short name such as "mm"'):
        read_calibration_unit(calib)


def test_a_calibration_that_names_no_unit_takes_the_one_given(tmp_path):
    """A par file names no unit: reconstruct --unit names it (a Middlebury set's metres); a
    calib.json naming another is refused in one line, and so is a unit that is no short name."""
    (tmp_path / "par.txt").write_text("2\n")
    assert read_calibration_unit(tmp_path / "par.txt", " m ") == "m"
    calib = tmp_path / "calib.json"
    write_json(calib, {"cameras": [], "unit": "mm"})
    assert read_calibration_unit(calib, "mm") == "mm"
    with pytest.raises(StereoseedError, match=r'calib.json names its unit "mm", not "m": leave --unit out'):
        read_calibration_unit(calib, "m")
    with pytest.raises(StereoseedError, match=r'--unit is ""; give a short name'):
        read_calibration_unit(tmp_path / "par.txt", "")
    assert length_text(0.2, "m") == "20 cm" and length_text(0.2, None) == "0.2 units"


def test_the_match_panel_draws_a_few_matches_spread_over_the_image():
    """717 matches, 700 of them crowded in one corner: the lines drawn are at most 60, every part
    of the image that has a match is among them, and each part gives its best first."""
    rng = np.random.default_rng(1)
    crowd = rng.uniform([0, 0], [80, 60], (700, 2))
    spread = rng.uniform([0, 0], [640, 480], (17, 2))
    points = np.vstack([crowd, spread])
    matches = Matches(np.arange(717), np.arange(717), rng.uniform(0.5, 1.0, 717).astype(np.float32))
    chosen = spread_matches(matches, points, (640, 480), 60)
    assert len(chosen) == 60 and len(set(chosen.tolist())) == 60
    assert set(range(700, 717)) <= set(chosen.tolist())  # the lone matches all drawn
    in_crowd = [i for i in chosen if i < 700]
    assert len(in_crowd) == 43
    # a dense run of a single cell: its best come first
    cell = Matches(np.arange(100), np.arange(100), np.linspace(0, 1, 100).astype(np.float32))
    assert spread_matches(cell, np.full((100, 2), 5.0), (640, 480), 10).tolist() == list(range(90, 100))
    assert spread_matches(cell, np.full((100, 2), 5.0), (640, 480), 200).tolist() == list(range(100))
