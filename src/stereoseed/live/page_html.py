"""The live page's HTML, CSS and script (served by :mod:`stereoseed.live.page`): the 3D view is
report.html's figure, drawn by the same Plotly bundle, served locally."""
from __future__ import annotations

__all__ = ["PAGE_HTML"]

PAGE_HTML = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{TITLE}}</title>
<style>
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;background:#f5f6f8;color:#1d2330}
header{background:#1f2430;color:#fff;padding:12px 20px}
header h1{margin:0 0 6px;font-size:19px;font-weight:600}
.summary{display:flex;flex-wrap:wrap;gap:4px 20px}.summary span{color:#9aa3b5;margin-right:5px;font-size:13px}
#connection{font-size:13px;color:#f6c177}
main{display:grid;grid-template-columns:minmax(0,2fr) minmax(300px,1fr);gap:14px;padding:14px 20px}
section{background:#fff;border-radius:6px;box-shadow:0 1px 3px rgba(0,0,0,.12);padding:8px 12px;margin-bottom:14px}
section h2{font-size:15px;margin:2px 0 6px}
#view3d{width:100%;height:560px}
#last.failed{color:#8a1c1c;font-weight:600}#last.flagged{color:#8a5a00;font-weight:600}
#hints li{margin:4px 0}#last-photo{max-width:100%;height:auto;border:1px solid #ccd}
#events{font-size:12px;max-height:260px;overflow-y:auto;margin:0;padding-left:18px}
#events li.warning{color:#8a5a00}
table{border-collapse:collapse;font-size:12px;width:100%;table-layout:fixed}
td{overflow-wrap:anywhere}
td,th{border-bottom:1px solid #e3e6ec;padding:3px 5px;text-align:left;vertical-align:top}
tr.failed td{background:#fde8e8;color:#8a1c1c}tr.flagged td{background:#fff1cc}
.note{color:#667;font-size:13px}
</style></head><body>
<header><h1>{{TITLE}}</h1><div class="summary">
<div><span>photos</span><b id="count-photos">0</b></div>
<div><span>cameras</span><b id="count-cameras">0</b></div>
<div><span>points</span><b id="count-points">0</b></div>
<div><span>skipped</span><b id="count-skipped">0</b></div>
<div><span>flagged</span><b id="count-flagged">0</b></div>
<div id="connection">connecting…</div></div></header>
<main><div>
<section><h2>Last photo</h2><p id="last" class="note">waiting for the first photo</p>
<img id="last-photo" alt="the last photo" hidden>
<p class="note">Green: its points that match the model; grey: the others.</p></section>
<section><h2>3D view</h2><div id="view3d"><p class="note">the model appears once the calibrated pair is in</p></div>
<p class="note">Orange: the calibrated pair; red: the cameras placed since. Drag to rotate, scroll to zoom.</p></section>
</div><div>
<section><h2>What to do next</h2><ul id="hints"></ul></section>
<section><h2>Photos</h2><table><thead><tr><th>photo</th><th>status</th><th>why</th></tr></thead>
<tbody id="photos"></tbody></table></section>
<section><h2>Log</h2><ol id="events"></ol></section>
</div></main>
<script src="/plotly.js"></script>
<script>
(function(){
  var config = {displaylogo: false, responsive: true}, drawn = false, shownVersion = 0;
  function webgl(){
    try { var c = document.createElement('canvas');
          return !!(window.WebGLRenderingContext && (c.getContext('webgl') || c.getContext('experimental-webgl'))); }
    catch (e) { return false; }
  }
  var hasWebGL = webgl();
  function text(id, value){ document.getElementById(id).textContent = value; }
  function cell(tr, value){ var td = document.createElement('td'); td.textContent = value == null ? '' : value; tr.appendChild(td); }
  function render(msg){
    var s = msg.state || {};
    text('count-photos', s.photos || 0); text('count-cameras', s.cameras || 0); text('count-points', s.points || 0);
    text('count-skipped', s.skipped || 0); text('count-flagged', s.flagged || 0);
    var last = document.getElementById('last');
    if (s.last) {
      var why = s.last.reason ? ': ' + s.last.reason : (s.last.flag ? ' but flagged: ' + s.last.flag : '');
      last.textContent = s.last.image + ': ' + s.last.status + why;
      last.className = s.last.status === 'failed' ? 'failed' : (s.last.flag ? 'flagged' : '');
    }
    var photo = document.getElementById('last-photo');
    if (s.last_photo) { photo.src = s.last_photo; photo.hidden = false; } else { photo.hidden = true; }
    var hints = document.getElementById('hints'); hints.innerHTML = '';
    (s.hints || []).forEach(function(h){ var li = document.createElement('li'); li.textContent = h; hints.appendChild(li); });
    var body = document.getElementById('photos'); body.innerHTML = '';
    (s.rows || []).forEach(function(r){
      var tr = document.createElement('tr');
      tr.className = r.status === 'failed' ? 'failed' : (r.flag ? 'flagged' : '');
      tr.setAttribute('data-image', r.image);
      cell(tr, r.image); cell(tr, r.status); cell(tr, r.reason || r.flag); body.appendChild(tr);
    });
    var events = document.getElementById('events'); events.innerHTML = '';
    (msg.events || []).forEach(function(e){
      var li = document.createElement('li'); li.className = e.level; li.textContent = e.t + '  ' + e.line; events.appendChild(li);
    });
    events.scrollTop = events.scrollHeight;
    var el = document.getElementById('view3d');
    if (s.figure && s.figure.data && s.figure.data.length) {
      if (!hasWebGL) { el.textContent = 'This browser has no WebGL: the 3D view cannot be drawn.'; }
      else if (window.Plotly) {
        if (!drawn) { el.innerHTML = ''; }
        Plotly.react(el, s.figure.data, s.figure.layout, config); drawn = true;
      }
    }
    shownVersion = msg.version;
    document.body.setAttribute('data-version', String(shownVersion));
  }
  var source = new EventSource('/events');
  source.onopen = function(){ text('connection', ''); };
  source.onerror = function(){ text('connection', 'connection to the run lost; retrying…'); };
  source.onmessage = function(e){ render(JSON.parse(e.data)); };
})();
</script></body></html>
"""
