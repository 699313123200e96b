"""Lengths in report.html: the model's unit (the calibration's, :func:`stereoseed.io.files.read_calibration_unit`),
a scale bar in the 3D view and the two-point distance readout (the page's script: click two
points of the 3D view).

A length is written in the unit the calibration named, or, when that unit is metric, in the
metric unit that gives it a number of at least 1 (0.05 m reads "5 cm"); a model whose unit is
unknown reads "units" (the calibration's, whatever they were)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["unit_label", "length_text", "round_length", "scale_bar", "MEASURE_SCRIPT"]

# metres per unit of the metric units a calibration may name; lengths in them are shown in the one
# that reads best
METRIC = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "km": 1e3}
SIGNIFICANT = 3  # digits of a length shown: a click on a point of the cloud is no better than that
SCALE_FRACTION = 0.2  # the scale bar is the round length nearest this fraction of the scene's extent
SCALE_COLOUR = "#ffd54f"  # yellow: apart from the clouds' colours and the frustums' orange and red


def unit_label(unit: str | None) -> str:
    """The unit as a column or axis title shows it: its name, or "units" when unknown."""
    return unit if unit else "units"


def _number(value: float) -> str:
    """``value`` to :data:`SIGNIFICANT` digits, positional, no trailing zeros (as the page's
    script writes it: ``String(Number(v.toPrecision(3)))``)."""
    return np.format_float_positional(float(f"{value:.{SIGNIFICANT}g}"), trim="-")


def length_text(value: float, unit: str | None) -> str:
    """A length of the model (``value`` in ``unit``) for people: "5 cm", "12.3 mm", "0.4 units"."""
    if unit in METRIC:
        metres = value * METRIC[unit]
        best = "mm"
        for name, size in METRIC.items():  # ascending: the largest unit that keeps the number >= 1
            if abs(metres) / size >= 1 - 1e-9:
                best = name
        return f"{_number(metres / METRIC[best])} {best}"
    return f"{_number(value)} {unit_label(unit)}"


def round_length(target: float) -> float:
    """The length of the 1-2-5 series (..., 0.1, 0.2, 0.5, 1, 2, 5, 10, ...) nearest ``target``
    (> 0) in ratio."""
    e = math.floor(math.log10(target))
    candidates = [m * 10.0 ** k for k in (e - 1, e, e + 1) for m in (1, 2, 5)]
    return min(candidates, key=lambda c: abs(math.log(c / target)))


def scale_bar(frame: dict[str, Any], points: np.ndarray, unit: str | None) -> dict[str, Any]:
    """A Plotly scatter3d trace: a segment of a round length (:func:`round_length` of
    :data:`SCALE_FRACTION` of the scene's largest extent) along the scene's first ground axis,
    with end ticks along 'up' and its length written above its middle, laid on the floor of the
    scene's points (of the scene's box when there are none), beyond their edge on the far side
    from where the view first looks (there the cloud and the frustums do not hide it).
    ``trace["meta"]``: its length in the model's unit."""
    extent = float(np.max(frame["hi"] - frame["lo"])) or frame["size"]
    length = round_length(SCALE_FRACTION * extent)
    e1, e2, up, target = frame["e1"], frame["e2"], frame["up"], frame["target"]
    pts = points if len(points) else np.vstack([frame["lo"], frame["hi"]])
    u, v, w = ((pts - target) @ axis for axis in (e1, e2, up))
    start = (target + float(np.percentile(u, 2)) * e1 + (float(np.percentile(v, 2)) - 0.05 * extent) * e2
             + float(np.percentile(w, 2)) * up)
    end = start + length * e1
    tick = 0.06 * length * up
    label = length_text(length, unit)
    segments = [start, 0.5 * (start + end), end, None, start - tick, start + tick, None, end - tick, end + tick]
    xyz = [[None if p is None else float(p[d]) for p in segments] for d in range(3)]
    return {"type": "scatter3d", "mode": "lines+text", "name": f"scale bar: {label}", "meta": length,
            "x": xyz[0], "y": xyz[1], "z": xyz[2], "text": ["", label, "", None, "", "", None, "", ""],
            "textposition": "top center", "textfont": {"color": SCALE_COLOUR, "size": 14},
            "line": {"color": SCALE_COLOUR, "width": 6}, "hoverinfo": "skip"}


def measurement_trace() -> dict[str, Any]:
    """The (empty) trace the page's script draws the measured points and their segment in."""
    return {"type": "scatter3d", "mode": "lines+markers", "name": "measured distance", "x": [], "y": [], "z": [],
            "line": {"color": "#00e5ff", "width": 5}, "marker": {"size": 5, "color": "#00e5ff"},
            "hoverinfo": "skip", "showlegend": False}


def measure_spec(unit: str | None, trace: int, skip: list[int]) -> dict[str, Any]:
    """What the page's script needs to measure in the 3D view: the unit, the metric table, the
    index of :func:`measurement_trace` and of the traces a click does not pick (the scale bar)."""
    return {"unit": unit or "", "metric": METRIC if unit in METRIC else None, "significant": SIGNIFICANT,
            "trace": trace, "skip": skip}


# Clicks on the 3D view: the first point, then the second and their distance; a third click starts
# again. The readout is #distance; the measured points are drawn in the measurement trace. Plotly
# says plotly_click at every frame it draws while the button is down on a point (and drawing the
# measurement draws a frame): one press of the button is one pick, and the drawing waits for the
# event to be over.
MEASURE_SCRIPT = """
function stereoseedMeasure(el, spec){
  var out = document.getElementById('distance');
  if (!out || !spec) return;
  var picks = [], armed = false;
  ['mousedown', 'touchstart'].forEach(function(type){
    el.addEventListener(type, function(){ armed = true; }, true);
  });
  function num(v){ return String(Number(v.toPrecision(spec.significant))); }
  function length(v){
    if (spec.metric) {
      var metres = v * spec.metric[spec.unit], best = 'mm';
      Object.keys(spec.metric).forEach(function(u){ if (Math.abs(metres) / spec.metric[u] >= 1 - 1e-9) best = u; });
      return num(metres / spec.metric[best]) + ' ' + best;
    }
    return num(v) + ' ' + (spec.unit || 'units');
  }
  function point(p){ return '(' + p.map(num).join(', ') + ')'; }
  el.on('plotly_click', function(ev){
    var p = ev && ev.points && ev.points[0];
    if (!armed || !p || p.curveNumber === spec.trace || spec.skip.indexOf(p.curveNumber) >= 0) return;
    var q = [Number(p.x), Number(p.y), Number(p.z)];
    if (!q.every(isFinite)) return;
    armed = false;
    if (picks.length >= 2) picks = [];
    picks.push(q);
    var drawn = picks.slice();
    setTimeout(function(){
      Plotly.restyle(el, {x: [drawn.map(function(a){ return a[0]; })], y: [drawn.map(function(a){ return a[1]; })],
                          z: [drawn.map(function(a){ return a[2]; })]}, [spec.trace]);
    }, 0);
    out.setAttribute('data-points', JSON.stringify(picks));
    if (picks.length === 1) {
      out.removeAttribute('data-distance');
      out.textContent = 'first point ' + point(q) + '; click a second point';
      return;
    }
    var d = Math.hypot(picks[1][0] - picks[0][0], picks[1][1] - picks[0][1], picks[1][2] - picks[0][2]);
    out.setAttribute('data-distance', String(d));
    out.textContent = 'distance: ' + length(d) + ' between ' + point(picks[0]) + ' and ' + point(picks[1]);
  });
}
"""
