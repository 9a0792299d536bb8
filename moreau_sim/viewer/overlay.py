"""The energy and gap plot added to the replay page (a 2D canvas that follows viser's slider),
and the escaping of the data it is given."""

from __future__ import annotations

import json
import re

import numpy as np


def label(x: float, digits: int = 3) -> str:
    """An axis label: `digits` significant digits, in exponent form below 1e-2 and from 1e3."""
    if x != 0 and (abs(x) < 1e-2 or abs(x) >= 1e3):
        return re.sub(r"e([+-])0*(\d)", r"e\1\2", f"{x:.{max(digits - 2, 1)}e}")
    return f"{x:.{digits}g}"


def axis(values, *, min_span: float, zero: bool = False) -> tuple[float, float, str, str]:
    """(lo, hi, label of lo, label of hi) of a plot axis over the finite `values` (and 0 if
    `zero`), widened about its middle to at least `min_span` > 0: never a degenerate axis, and
    its labels given the fewest significant digits (at least 3) that tell them apart."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    lo, hi = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)
    if zero:
        lo, hi = min(lo, 0.0), max(hi, 0.0)
    if not hi - lo >= min_span:
        mid = 0.5 * (lo + hi)
        lo, hi = mid - 0.5 * min_span, mid + 0.5 * min_span
    for digits in range(3, 18):
        a, b = label(lo, digits), label(hi, digits)
        if a != b:
            break
    return lo, hi, a, b


def js_string(value) -> str:
    """JSON for an inline <script>: no "<", ">", "&" or line separators left raw, so no scene text
    can close the element or open a comment."""
    s = json.dumps(value, separators=(",", ":"), allow_nan=False, ensure_ascii=True)
    return s.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


OVERLAY = r"""
<style>
#ms-panel{position:fixed;right:10px;top:10px;z-index:3;background:rgba(255,255,255,.93);border:1px solid #d5d9de;
border-radius:6px;padding:6px 8px;font:12px system-ui,sans-serif;color:#222;box-shadow:0 1px 6px rgba(0,0,0,.12)}
#ms-title{font-weight:600;max-width:330px;overflow:hidden;text-overflow:ellipsis;white-space:nowrap}
#ms-desc{max-width:330px;color:#555;display:none;white-space:normal;max-height:140px;overflow:auto}
#ms-title:hover+#ms-desc{display:block}
#ms-legend span{margin-right:8px;white-space:nowrap}
</style>
<div id="ms-panel"><div id="ms-title"></div><div id="ms-desc"></div>
<canvas id="ms-plot" width="330" height="150"></canvas><div id="ms-legend"></div></div>
<script>
(function(){
const D = __MS_DATA__;
window.moreauReplay = {ready:false, t:0, frame:0, error:null};
function start(){
  document.title = D.scene + " - moreau-sim replay";
  document.getElementById("ms-title").textContent = D.scene + "  (e = " + D.restitution + ", dt = " + D.dt + " s)";
  document.getElementById("ms-desc").textContent = D.description;
  const cv = document.getElementById("ms-plot"), g = cv.getContext("2d");
  const W = cv.width, H = cv.height, L = 44, R = 8, hE = 78, top = 6, gTop = 96, hG = 44;
  const t = D.t, t0 = t[0], t1 = t[t.length-1] > t0 ? t[t.length-1] : t0 + 1;
  const X = x => L + (W-L-R)*(x-t0)/(t1-t0);
  const ser = [["E = T + V", D.energy, "#222"], ["T", D.kinetic, "#3b82c4"], ["V", D.potential, "#4caf6a"]];
  const [lo, hi] = D.energy_axis, [glo, ghi] = D.gap_axis;  // limits and labels made by overlay.axis
  const YE = y => top + hE*(1-(y-lo)/(hi-lo));
  const YG = y => gTop + hG*(1-(y-glo)/(ghi-glo));
  function draw(tc){
    g.clearRect(0,0,W,H); g.font = "10px system-ui,sans-serif"; g.lineWidth = 1;
    g.strokeStyle = "#ccc"; g.strokeRect(L, top, W-L-R, hE); g.strokeRect(L, gTop, W-L-R, hG);
    g.fillStyle = "#555"; g.fillText(D.energy_labels[1], 2, top+8); g.fillText(D.energy_labels[0], 2, top+hE);
    g.fillText("J", 2, top+hE/2+4);
    g.fillText(D.gap_labels[1], 2, gTop+8); g.fillText(D.gap_labels[0], 2, gTop+hG);
    g.fillText("gap m", 2, gTop+hG/2+4);
    g.fillText(t0.toFixed(2)+" s", L, H-2); g.fillText(t1.toFixed(2)+" s", W-R-36, H-2);
    if (glo < 0 && ghi > 0) {
      g.strokeStyle = "#e0a0a0"; g.beginPath(); g.moveTo(L, YG(0)); g.lineTo(W-R, YG(0)); g.stroke();
    }
    for (const [name, ys, col] of ser.concat([["min gap", D.gap, "#c8455a"]])) {
      const Y = name === "min gap" ? YG : YE;
      g.strokeStyle = col; g.lineWidth = name === "E = T + V" ? 1.6 : 1; g.beginPath();
      ys.forEach((y, i) => i ? g.lineTo(X(t[i]), Y(y)) : g.moveTo(X(t[i]), Y(y))); g.stroke();
    }
    g.strokeStyle = "#e0202a"; g.lineWidth = 1.5; g.beginPath();
    g.moveTo(X(tc), top); g.lineTo(X(tc), gTop+hG); g.stroke();
  }
  document.getElementById("ms-legend").innerHTML = "";
  for (const [name, , col] of ser.concat([["min gap", null, "#c8455a"]])) {
    const s = document.createElement("span"); s.style.color = col; s.textContent = "\u25a0 " + name;
    document.getElementById("ms-legend").appendChild(s);
  }
  let last = null;
  function tick(){
    const el = document.querySelector('[role="slider"][aria-valuenow]');
    const tc = el ? t0 + parseFloat(el.getAttribute("aria-valuenow")) : t0;
    if (tc !== last) { last = tc; draw(tc);
      let k = 0; while (k + 1 < t.length && t[k+1] <= tc + 1e-9) k++;
      window.moreauReplay.t = tc; window.moreauReplay.frame = k; }
    window.moreauReplay.ready = !!el && !!document.querySelector("canvas:not(#ms-plot)");
    requestAnimationFrame(tick);
  }
  draw(t0); tick();
}
try { if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start); else start(); }
catch (e) { window.moreauReplay.error = String(e); }
})();
</script>
"""
