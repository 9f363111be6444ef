"""``freescale report STORE [-o report.html]``: one self-contained HTML file for a store.

Everything is inline (figures as base64 ``data:`` URIs, CSS, a small script), so the file
opens offline, from an e-mail or a CI artifact, with no server and no CDN. Per scene: its
status and counts, the error of a failed scene, the figures of its current version and a 3D
view of the cameras (training path, free views by mode, the certainty box) that the reader
turns by dragging (an orthographic projection drawn on a canvas by the inline script).
"""

from __future__ import annotations

import base64
import html
import json
import math
import time
from pathlib import Path

import numpy as np

from freescale_core.store.store import Store

__all__ = ["write_report", "render_report", "scene_cameras"]

FIGURE_ORDER = ("funnel.png", "cameras.png", "scores.png", "certainty.png", "contact_sheet.png")
TABLE_ROWS = (("status", "status"), ("n_images", "training views"),
              ("n_gaussians", "Gaussians"), ("n_candidates", "candidates"),
              ("n_feasible", "feasible"), ("n_selected", "NMS-selected"),
              ("n_rejected", "rejected by the filter"), ("n_free_views", "free views"),
              ("scarce", "scarce (< target)"), ("recon_train_psnr", "train PSNR (dB)"),
              ("recon_test_psnr", "test PSNR (dB)"), ("seconds_total", "seconds"),
              ("version", "version"), ("config_hash", "config"))


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.2f}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def scene_cameras(store: Store, scene_id: str, max_suppressed: int = 400) -> dict | None:
    """Camera centres and view directions of a scene's current version, for the 3D view."""
    d = store.current_version_dir(scene_id)
    if d is None or not (d / "views.parquet").is_file():
        return None
    import pyarrow.parquet as pq

    from freescale_core.store.layout import world_from_cam_column

    t = pq.read_table(d / "views.parquet", columns=["kind", "mode", "disposition",
                                                     "world_from_cam", "view_id"])
    wfc = world_from_cam_column(t)
    disp = np.asarray(t.column("disposition").to_pylist())
    mode = np.asarray(t.column("mode").to_pylist())
    keep = np.flatnonzero(np.isin(disp, ["train", "free_view"]))
    sup = np.flatnonzero(disp == "suppressed")
    if len(sup) > max_suppressed:
        sup = sup[np.linspace(0, len(sup) - 1, max_suppressed).astype(int)]
    idx = np.concatenate([keep, sup])
    box = None
    try:
        import zarr

        a = zarr.open_group(str(d / "arrays.zarr"), mode="r")["certainty"]
        box = [list(map(float, a.attrs["bbox_min"])), list(map(float, a.attrs["bbox_max"]))]
    except Exception:  # noqa: BLE001 - the 3D view works without the box
        box = None
    # a frame with z = the scene's up (the training cameras' mean -y axis, OpenCV axes), so
    # the view opens upright whatever the world convention of the capture
    from freescale_core.store.figures import _basis

    train = disp == "train"
    up = -wfc[train, :3, 1].mean(axis=0) if train.any() else np.array([0.0, 0.0, 1.0])
    if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-9:
        up = np.array([0.0, 0.0, 1.0])
    B = np.stack(_basis(up))  # rows e1, e2, up
    r = lambda x: [round(float(v), 4) for v in x]  # noqa: E731
    if box is not None:  # the box's 8 corners in that frame
        lo, hi = np.asarray(box[0]), np.asarray(box[1])
        box = [r(B @ np.array([(lo, hi)[i & 1][0], (lo, hi)[(i >> 1) & 1][1],
                               (lo, hi)[(i >> 2) & 1][2]])) for i in range(8)]
    return {"c": [r(B @ p) for p in wfc[idx, :3, 3]], "f": [r(B @ p) for p in wfc[idx, :3, 2]],
            "k": [("train" if disp[i] == "train" else
                   "suppressed" if disp[i] == "suppressed" else str(mode[i])) for i in idx],
            "box": box}


def _img(p: Path) -> str:
    b64 = base64.b64encode(p.read_bytes()).decode()
    alt = html.escape(p.stem.replace("_", " "))
    return f'<figure><img alt="{alt}" src="data:image/png;base64,{b64}"><figcaption>{alt}</figcaption></figure>'


def _scene_html(store: Store, row: dict, k: int) -> tuple[str, dict | None]:
    sid = str(row.get("scene_id"))
    status = row.get("status")
    cls = "ok" if status == "ok" else "failed" if status == "failed" else "other"
    out = [f'<section class="scene" id="scene-{k}"><h2>{html.escape(sid)} '
           f'<span class="badge {cls}">{html.escape(str(status))}</span></h2>']
    if row.get("error"):
        out.append(f'<p class="error"><b>error</b> ({html.escape(str(row.get("error_type") or ""))})'
                   f": <code>{html.escape(str(row['error']))}</code></p>")
    out.append('<table class="kv">')
    for key, label in TABLE_ROWS:
        if row.get(key) not in (None, ""):
            out.append(f"<tr><th>{label}</th><td>{html.escape(_fmt(row.get(key)))}</td></tr>")
    out.append("</table>")
    cams = scene_cameras(store, sid) if status == "ok" else None
    if cams:
        out.append(f'<div class="view3d"><canvas id="cam3d-{k}" width="640" height="420" '
                   f'data-scene="{k}" aria-label="3D cameras of {html.escape(sid)}"></canvas>'
                   '<p class="hint">drag to turn, wheel to zoom: training path (black), free '
                   'views by mode, suppressed candidates (grey), certainty box</p></div>')
    d = store.current_version_dir(sid)
    if d is not None and status == "ok":
        figs = [d / n for n in FIGURE_ORDER if (d / n).is_file()]
        out.append('<div class="figs">' + "".join(_img(p) for p in figs) + "</div>")
    out.append("</section>")
    return "\n".join(out), cams


_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:0 auto;max-width:1280px;padding:16px;color:#222}
h1{font-size:22px}h2{font-size:18px;border-bottom:1px solid #ddd;padding-bottom:4px}
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ddd;padding:3px 8px;text-align:left}
th{background:#f4f4f4}.kv th{width:200px}.badge{font-size:12px;padding:2px 8px;border-radius:9px}
.ok{background:#d8f3dc;color:#1b4332}.failed{background:#ffd6d6;color:#7a0000}.other{background:#eee}
.error{background:#fff3f3;border-left:4px solid #c00;padding:6px 10px}
.figs img{max-width:100%;border:1px solid #eee}figure{margin:10px 0}
figcaption{color:#666;font-size:12px}canvas{border:1px solid #ccc;background:#fff;cursor:grab}
.hint{color:#666;font-size:12px;margin:2px 0}.legend span{display:inline-block;margin-right:10px;font-size:12px}
"""

# Orthographic 3D view on a canvas, turned by mouse drag; no libraries.
_JS = r"""
(function(){
"use strict";
var DATA = JSON.parse(document.getElementById("cam-data").textContent);
var COLORS = JSON.parse(document.getElementById("mode-colors").textContent);
function View(cv, d){
  var ctx = cv.getContext("2d"), yaw = 0.6, pitch = 0.5, zoom = 1.0, drag = null;
  var pts = d.c, n = pts.length, mid = [0,0,0], span = 1e-9, i, j;
  for (i = 0; i < n; i++) for (j = 0; j < 3; j++) mid[j] += pts[i][j] / n;
  var box = d.box, corners = box || [];
  var all = pts.concat(corners);
  for (i = 0; i < all.length; i++) span = Math.max(span, Math.hypot(all[i][0]-mid[0], all[i][1]-mid[1], all[i][2]-mid[2]));
  var arrow = 0.06 * span;
  // z is up (the scene's up); yaw turns about it, pitch tilts towards the viewer
  function proj(p){
    var x = p[0]-mid[0], y = p[1]-mid[1], z = p[2]-mid[2];
    var cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    var x1 = cy*x - sy*y, y1 = sy*x + cy*y;
    var v = sp*y1 + cp*z, depth = cp*y1 - sp*z;
    var s = zoom * 0.45 * Math.min(cv.width, cv.height) / span;
    return [cv.width/2 + s*x1, cv.height/2 - s*v, depth];
  }
  function draw(){
    ctx.clearRect(0, 0, cv.width, cv.height);
    if (box && corners.length === 8) {
      ctx.strokeStyle = "#888"; ctx.lineWidth = 1; ctx.beginPath();
      for (var a = 0; a < 8; a++) for (var b = a+1; b < 8; b++) {
        var x = a ^ b; if (x === 1 || x === 2 || x === 4) {
          var pa = proj(corners[a]), pb = proj(corners[b]); ctx.moveTo(pa[0], pa[1]); ctx.lineTo(pb[0], pb[1]); } }
      ctx.stroke();
    }
    var order = [];
    for (i = 0; i < n; i++) order.push([proj(pts[i]), i]);
    order.sort(function(u, v){ return v[0][2] - u[0][2]; });
    ctx.beginPath(); ctx.strokeStyle = "rgba(0,0,0,0.5)"; var first = true;
    for (i = 0; i < n; i++) if (d.k[i] === "train") { var q = proj(pts[i]); if (first) { ctx.moveTo(q[0], q[1]); first = false; } else ctx.lineTo(q[0], q[1]); }
    ctx.stroke();
    for (var o = 0; o < order.length; o++) {
      var p = order[o][0], k = order[o][1], kind = d.k[k];
      var col = kind === "train" ? "#000" : kind === "suppressed" ? "#bbb" : (COLORS[kind] || "#333");
      var f = d.f[k], tip = proj([pts[k][0]+arrow*f[0], pts[k][1]+arrow*f[1], pts[k][2]+arrow*f[2]]);
      if (kind !== "suppressed") { ctx.strokeStyle = col; ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(tip[0], tip[1]); ctx.stroke(); }
      ctx.fillStyle = col; ctx.beginPath(); ctx.arc(p[0], p[1], kind === "suppressed" ? 1.5 : 3, 0, 2*Math.PI); ctx.fill();
    }
    ctx.fillStyle = "#444"; ctx.font = "12px sans-serif";
    ctx.fillText("yaw " + (yaw*180/Math.PI).toFixed(0) + " deg, pitch " + (pitch*180/Math.PI).toFixed(0) + " deg", 8, cv.height - 8);
  }
  cv.addEventListener("mousedown", function(e){ drag = [e.clientX, e.clientY]; });
  window.addEventListener("mouseup", function(){ drag = null; });
  window.addEventListener("mousemove", function(e){
    if (!drag) return;
    yaw += (e.clientX - drag[0]) * 0.01; pitch += (e.clientY - drag[1]) * 0.01;
    pitch = Math.max(-1.55, Math.min(1.55, pitch)); drag = [e.clientX, e.clientY]; draw(); });
  cv.addEventListener("wheel", function(e){ e.preventDefault(); zoom *= e.deltaY < 0 ? 1.1 : 1/1.1; draw(); }, {passive: false});
  draw();
}
var cvs = document.querySelectorAll("canvas[data-scene]");
for (var c = 0; c < cvs.length; c++) { var d = DATA[cvs[c].getAttribute("data-scene")]; if (d) View(cvs[c], d); }
})();
"""


def render_report(store: Store, problems: list[str] | None = None) -> str:
    """The report's HTML text. A scene whose published files cannot be read (a damaged
    ``views.parquet``) is shown with status ``unreadable`` and the error, the other scenes as
    usual; one line per such scene is appended to ``problems``."""
    from freescale_core.store.figures import MODE_COLORS

    rows = store.manifest().to_pylist()
    sections, cams = [], {}
    for k, r in enumerate(rows):
        try:
            s, c = _scene_html(store, r, k)
        except Exception as e:  # noqa: BLE001 - one damaged scene never hides the others
            d = store.current_version_dir(str(r.get("scene_id")))
            msg = " ".join(str(e).split())[:300] or type(e).__name__
            r.update(status="unreadable", error_type=type(e).__name__,
                     error=f"scene '{r.get('scene_id')}': its published files cannot be read "
                           f"({msg}) [{d}]")
            if problems is not None:
                problems.append(r["error"])
            s, c = _scene_html(store, r, k)
        sections.append(s)
        if c:
            cams[str(k)] = c
    n_ok = sum(r.get("status") == "ok" for r in rows)
    n_free = sum(int(r.get("n_free_views") or 0) for r in rows)
    head = ["scene", "status", "training views", "free views", "scarce", "train PSNR",
            "seconds", "error"]
    summ = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for k, r in enumerate(rows):
        cls = "ok" if r.get("status") == "ok" else "failed"
        err = str(r.get("error") or "")
        summ.append(
            f'<tr><td><a href="#scene-{k}">{html.escape(str(r.get("scene_id")))}</a></td>'
            f'<td class="{cls}">{html.escape(str(r.get("status")))}</td>'
            + "".join(f"<td>{html.escape(_fmt(r.get(c)))}</td>" for c in
                      ("n_images", "n_free_views", "scarce", "recon_train_psnr", "seconds_total"))
            + f"<td>{html.escape(err[:160])}</td></tr>")
    summ.append("</table>")
    legend = "".join(f'<span style="color:{c}">&#9679; {m}</span>' for m, c in MODE_COLORS.items())
    title = f"FreeScale store {store.root}"
    # "</" inside a <script> block would end it early; JSON never needs it unescaped
    data = json.dumps(cams).replace("</", "<\\/")
    return "\n".join([
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>{len(rows)} scenes: {n_ok} ok, {len(rows) - n_ok} not ok; {n_free} free views. "
        f"Written {time.strftime('%Y-%m-%d %H:%M:%S %Z')}. Columns: docs/STORE.md.</p>",
        *summ, f'<p class="legend">{legend}</p>', *sections,
        f'<script type="application/json" id="cam-data">{data}</script>',
        f'<script type="application/json" id="mode-colors">{json.dumps(MODE_COLORS)}</script>',
        f"<script>{_JS}</script>", "</body></html>"])


def write_report(store: Store, out: str | Path, problems: list[str] | None = None) -> Path:
    """Write the report atomically to ``out`` (``problems``: see :func:`render_report`)."""
    from freescale_core.store.store import write_bytes_atomic

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out, render_report(store, problems).encode())
    return out
