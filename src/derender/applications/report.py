"""A self-contained HTML report of a radiance map: look at it, read values, see the uncertainty.

An HDR merge ends in an EXR most people cannot open. :func:`write_report` writes one HTML file
that works offline (no server, no CDN: data and script are embedded) and shows

* the map tone-mapped in the page from its float data, with an exposure slider (EV) and a
  choice of operator (linear with exposure, Reinhard's global operator ``L / (1 + L)``);
* falsecolor luminance on a log scale with a legend (cd/m² when the map is absolute, e.g.
  after ``derender merge --spot``; relative units otherwise);
* the relative uncertainty ``sigma / mu`` of the luminance when a variance exists (stored as
  the variance of ``Y = w . RGB``, channels independent: one plane, not three);
* overlays of the masks (pixels over-exposed in every frame, ghosts, uncovered);
* the response curves, when the merge recovered some;
* a summary: a merge's one record (:class:`derender.hdr.summary.MergeSummary`: method, frames
  with exposure times, f-numbers and ISO, reference, alignment shifts, clipped and taken
  pixels, numbered and counted as ``derender merge`` prints them), read from the map's header
  by ``derender report``; the illuminance with its uncertainty when a view is known;
* a readout under the cursor (mouse, or the arrow keys on the focused image): linear RGB,
  luminance and its standard deviation at that pixel.

Size: the map is reduced by an integer factor to at most ``max_pixels`` (area average, as
the readout says), scaled by a power of two that puts its brightest value near 2^14 (so no
value falls into the half floats' subnormal range unless it is 2^-28 below the top), stored
as half floats rounded to :data:`RGB_MANTISSA_BITS` mantissa bits,
their two bytes split into planes (the exponent bytes of a smooth image compress several
times better apart) and gzip-compressed,
then base64-encoded into the page; the browser inflates it with its own
``DecompressionStream`` (Chromium >= 80, Firefox >= 113). Readout values are the reduced
map's: the mean radiance of the ``factor x factor`` block under the cursor.
"""

from __future__ import annotations

import base64
import gzip
import html
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from derender.core.errors import InputError

__all__ = ["REPORT_MAX_PIXELS", "RGB_MANTISSA_BITS", "VAR_MANTISSA_BITS", "reduce_map", "pack_half", "write_report"]

#: Default largest number of pixels the page holds (a 24 MP merge is reduced by 5: 0.96 MP; the
#: iPhone bracket's 8 MP by 3: 816x1088, still more than the page shows at 1:1). The page data
#: is the map's noise, which no lossless coder removes, so its size follows the pixel count:
#: the iPhone report with a variance was 9.76 MB at 2 MP (radiance 7.08 MB, standard
#: deviation 2.66 MB) and is 3.7 MB at 1 MP with the bits below (issue 37).
REPORT_MAX_PIXELS = 1_000_000

#: Mantissa bits kept of the radiance's half floats: relative error <= 2^-8 = 0.4 % (the
#: readout's 1 % promise); 7 bits instead of 8 saved 13 % of the radiance's bytes on the
#: iPhone bracket (3.13 -> 2.73 MB at 1 MP).
RGB_MANTISSA_BITS = 7

#: Mantissa bits kept of the luminance's standard deviation (stored instead of the variance: a
#: variance spans twice the decades, and dark pixels fell into the half floats' subnormals):
#: relative error <= 2^-7 = 0.8 % of an uncertainty (within the readout's 1 %).
VAR_MANTISSA_BITS = 6


def reduce_map(image: np.ndarray, max_pixels: int = REPORT_MAX_PIXELS) -> tuple[np.ndarray, int]:
    """Area-average ``image`` (H, W, ...) by the smallest integer factor that brings it to at
    most ``max_pixels`` pixels; returns (reduced float32 array, factor). Edge rows and columns
    that do not fill a block are left out."""
    a = np.asarray(image, dtype=np.float32)
    h, w = a.shape[:2]
    f = 1
    while (h // f) * (w // f) > max_pixels:
        f += 1
    if f == 1:
        return np.ascontiguousarray(a), 1
    hh, ww = h // f, w // f
    blocks = a[:hh * f, :ww * f].reshape(hh, f, ww, f, *a.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32), f


def pack_half(values: np.ndarray, mantissa_bits: int = 10) -> str:
    """float16 values rounded to ``mantissa_bits`` of their 10 mantissa bits (relative error
    <= 2^-(bits+1)), low and high bytes in separate planes, gzip (level 6: level 9 took 2.2x the time for 0.8 % less), base64."""
    if not 1 <= mantissa_bits <= 10:
        raise InputError(f"mantissa_bits must be 1..10, got {mantissa_bits}")
    u = np.ascontiguousarray(np.asarray(values, dtype=np.float16)).view(np.uint16).reshape(-1)
    drop = 10 - int(mantissa_bits)
    if drop:
        half_step = np.uint16(1 << (drop - 1))
        finite = (u & 0x7C00) != 0x7C00
        rounded = ((u.astype(np.uint32) + half_step) & (0xFFFF ^ ((1 << drop) - 1))).astype(np.uint16)
        # a carry into the exponent is the correct rounding up; never round a finite value to inf
        u = np.where(finite & ((rounded & 0x7C00) != 0x7C00), rounded, u)
    h16 = u.view(np.uint8).reshape(-1, 2)
    planes = np.concatenate([h16[:, 0], h16[:, 1]]).tobytes()
    return base64.b64encode(gzip.compress(planes, compresslevel=6, mtime=0)).decode("ascii")


def _half_scale(values: np.ndarray) -> float:
    """The power of two that puts the largest of ``values`` near 2^14 (1 when none is positive)."""
    top = float(np.max(values)) if values.size else 0.0
    return float(2.0 ** np.floor(np.log2(16384.0 / top))) if top > 0 else 1.0


def _pack_bytes(values: np.ndarray) -> str:
    return base64.b64encode(gzip.compress(np.ascontiguousarray(values, dtype=np.uint8).tobytes(), 6,
                                          mtime=0)).decode("ascii")


def write_report(path: str | os.PathLike, radiance: np.ndarray, *, variance: np.ndarray | None = None,
                 mask: np.ndarray | None = None, ghost_mask: np.ndarray | None = None,
                 absolute: bool = False, primaries=None, summary: dict[str, Any] | None = None,
                 curves: np.ndarray | None = None, view=None, title: str = "derender report",
                 max_pixels: int = REPORT_MAX_PIXELS, inputs=()) -> dict[str, Any]:
    """Write the report (module docstring) atomically; returns ``{"factor", "width",
    "height", "bytes"}``. ``mask``: ``HDRResult.mask`` codes (1 over-exposed, 2
    under-exposed everywhere) or the 0/128/255 PNG codes; ``ghost_mask``: nonzero where frames
    were rejected; ``curves``: (256, 3) ``ln f^-1``; ``view``: a
    :class:`derender.photometry.projection.View` (the summary then gives Ev)."""
    from derender.io.files import atomic_output
    from derender.photometry.illuminance import luminance_weights, vertical_illuminance

    rad = np.asarray(radiance, dtype=np.float32)
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise InputError(f"a radiance map is (H, W, 3), got {rad.shape}")
    if not np.all(np.isfinite(rad)):
        raise InputError("the radiance map has non-finite values")
    h, w = rad.shape[:2]
    for name, arr in (("variance", variance), ("mask", mask), ("ghost mask", ghost_mask)):
        if arr is not None and np.asarray(arr).shape[:2] != (h, w):
            raise InputError(f"the {name} is {np.asarray(arr).shape[1]}x{np.asarray(arr).shape[0]}, the map {w}x{h}")
    small, f = reduce_map(rad, max_pixels)
    sh, sw = small.shape[:2]
    # a power of two that puts the brightest value near 2^14: half floats then keep their relative
    # precision down to 2^-14 of it (normal range), whatever the map's units
    pscale = _half_scale(small)
    data: dict[str, Any] = {"width": sw, "height": sh, "factor": f, "full": [w, h], "absolute": bool(absolute),
                            "weights": [float(v) for v in luminance_weights(primaries)],
                            "scale": pscale, "rgb": pack_half(np.clip(small * pscale, 0, 65000), RGB_MANTISSA_BITS)}
    if variance is not None:
        # the variance of Y = w . RGB (channels independent), of the block mean (pixels independent: / f^2)
        wts = luminance_weights(primaries)
        var_y = np.clip(np.asarray(variance, dtype=np.float32), 0, None) @ (wts * wts).astype(np.float32)
        v_small, _ = reduce_map(var_y, max_pixels)
        sd_small = np.sqrt(v_small / (f * f))        # stored as a standard deviation: half the decades of a variance
        vscale = _half_scale(sd_small)
        data["varscale"] = vscale
        data["var"] = pack_half(np.clip(sd_small * vscale, 0, 65000), VAR_MANTISSA_BITS)
    overlays = np.zeros((sh, sw), np.uint8)
    if mask is not None:
        m = np.asarray(mask)
        m = m[..., 0] if m.ndim == 3 else m
        clipped = ((m == 1) | (m == 128)).astype(np.float32)
        dark = ((m == 2) | (m == 255)).astype(np.float32)
        overlays |= (reduce_map(clipped, max_pixels)[0] > 0).astype(np.uint8) * 1
        overlays |= (reduce_map(dark, max_pixels)[0] > 0).astype(np.uint8) * 4
    if ghost_mask is not None:
        g = np.asarray(ghost_mask)
        g = (g[..., 0] if g.ndim == 3 else g) != 0
        overlays |= (reduce_map(g.astype(np.float32), max_pixels)[0] > 0).astype(np.uint8) * 2
    data["overlays"] = _pack_bytes(overlays)
    if curves is not None:
        c = np.asarray(curves, dtype=np.float64)
        if c.ndim == 2 and c.shape[1] == 3:
            data["curves"] = [[round(float(v), 5) for v in row] for row in c]
    info = dict(summary or {})
    if mask is not None and "taken from the shortest exposure (mask)" not in info:
        m = np.asarray(mask)
        m = m[..., 0] if m.ndim == 3 else m
        n = int(np.count_nonzero((m == 1) | (m == 128)))
        info["taken from the shortest exposure (mask)"] = f"{n} px ({100 * n / m.size:.2f} %)"
    if view is not None:
        ev = vertical_illuminance(rad, view, primaries=primaries, variance=variance)
        sd = f" ± {ev.ev_sd:.4g}" if ev.ev_sd is not None else ""
        info["vertical illuminance Ev"] = f"{ev.ev:.5g}{sd} {'lx' if absolute else '(relative)'} ({view.header()})"
    data["summary"] = {str(k): (v if isinstance(v, (str, int, float)) else json.dumps(v, default=str))
                       for k, v in info.items()}
    page = _PAGE.replace("__TITLE__", html.escape(title)).replace("__DATA__", json.dumps(data))
    path = Path(path)
    with atomic_output(path, inputs) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return {"factor": f, "width": sw, "height": sh, "bytes": path.stat().st_size}


_PAGE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,sans-serif;margin:1em;background:#1b1b1b;color:#eee}
h1{font-size:1.3em} .row{display:flex;gap:1.2em;flex-wrap:wrap;align-items:flex-start}
canvas{image-rendering:pixelated;border:1px solid #555} #img:focus{outline:2px solid #6af}
fieldset{border:1px solid #555;margin:0 0 .6em 0} label{margin-right:.8em}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #444;padding:2px 6px;text-align:left}
#readout{font-family:ui-monospace,monospace;white-space:pre;min-height:5em}
</style></head>
<body>
<h1>__TITLE__</h1>
<div class="row">
<div>
<fieldset><legend>View</legend>
<label><input type="radio" name="mode" value="tone" checked> tone-mapped</label>
<label><input type="radio" name="mode" value="false"> falsecolor luminance</label>
<label id="uncLabel"><input type="radio" name="mode" value="unc"> relative uncertainty σ/μ</label>
</fieldset>
<fieldset><legend>Tone mapping</legend>
<label for="ev">exposure (EV)</label><input type="range" id="ev" min="-12" max="12" step="0.25" value="0" aria-label="exposure in EV">
<output id="evOut">0 EV</output>
<label for="op">operator</label><select id="op" aria-label="tone-mapping operator"><option value="linear">linear</option><option value="reinhard" selected>Reinhard</option></select>
</fieldset>
<fieldset><legend>Overlays</legend>
<label><input type="checkbox" id="ovClip"> over-exposed in every frame (red)</label>
<label><input type="checkbox" id="ovGhost"> ghosts (magenta)</label>
<label><input type="checkbox" id="ovDark"> under-exposed everywhere (blue)</label>
</fieldset>
<canvas id="img" tabindex="0" aria-label="radiance map; arrow keys move the readout cursor"></canvas>
<div><canvas id="legend" width="420" height="56" aria-label="colour legend"></canvas></div>
</div>
<div>
<h2>Under the cursor</h2><div id="readout" aria-live="polite">move the mouse over the image, or focus it and use the arrow keys</div>
<h2>Summary</h2><table id="summary"></table>
<div id="curvesBox"><h2>Response curves</h2><canvas id="curves" width="420" height="300" aria-label="response curves"></canvas></div>
</div></div>
<script>
"use strict";
const D = __DATA__;
const W = D.width, H = D.height, WT = D.weights;
async function inflate(b64){
  const bin = Uint8Array.from(atob(b64), c => c.charCodeAt(0));
  const stream = new Blob([bin]).stream().pipeThrough(new DecompressionStream("gzip"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}
function halfToFloat(h){
  const s = (h & 0x8000) ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
  if (e === 0) return s * Math.pow(2, -14) * (f / 1024);
  if (e === 31) return f ? NaN : s * Infinity;
  return s * Math.pow(2, e - 15) * (1 + f / 1024);
}
async function halves(b64){
  const bytes = await inflate(b64), n = bytes.length / 2, out = new Float32Array(n);
  for (let i = 0; i < n; i++) out[i] = halfToFloat(bytes[i] | (bytes[n + i] << 8));
  return out;
}
function lumAt(rgb, i){ return 179 * (WT[0]*rgb[3*i] + WT[1]*rgb[3*i+1] + WT[2]*rgb[3*i+2]); }
function viridis(t){  // matplotlib's viridis, 9 stops, linear in between
  const c=[[68,1,84],[71,44,122],[59,81,139],[44,113,142],[33,144,141],[39,173,129],[92,200,99],[170,220,50],[253,231,37]];
  t = Math.min(1, Math.max(0, t)) * 8; const k = Math.min(7, Math.floor(t)), u = t - k;
  return c[k].map((v, j) => v + u * (c[k+1][j] - v));
}
let RGB, VAR = null, OV = null, cursor = null;
const img = document.getElementById("img"), ctx = img.getContext("2d");
img.width = W; img.height = H;
const scale = Math.max(1, Math.floor(Math.min(900 / W, 700 / H)));
img.style.width = (W * scale) + "px"; img.style.height = (H * scale) + "px";
let lumTop = 1, lumBottom = 1e-4;
function enc(v){ v = Math.min(1, Math.max(0, v)); return 255 * (v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1/2.4) - 0.055); }
function draw(){
  const mode = document.querySelector('input[name="mode"]:checked').value;
  const ev = parseFloat(document.getElementById("ev").value), k = Math.pow(2, ev);
  const op = document.getElementById("op").value;
  document.getElementById("evOut").textContent = ev + " EV";
  const im = ctx.createImageData(W, H), px = im.data;
  const ovc = document.getElementById("ovClip").checked, ovg = document.getElementById("ovGhost").checked,
        ovd = document.getElementById("ovDark").checked;
  const lt = Math.log10(lumTop), lb = Math.log10(lumBottom);
  for (let i = 0; i < W * H; i++){
    let r, g, b;
    if (mode === "tone"){
      r = RGB[3*i]*k; g = RGB[3*i+1]*k; b = RGB[3*i+2]*k;
      if (op === "reinhard"){ r = r/(1+r); g = g/(1+g); b = b/(1+b); }
      r = enc(r); g = enc(g); b = enc(b);
    } else if (mode === "false"){
      const L = lumAt(RGB, i); const t = L > 0 ? (Math.log10(L) - lb) / (lt - lb) : 0;
      [r, g, b] = viridis(t);
    } else {
      const Y = lumAt(RGB, i) / 179, v = VAR[i];
      const rel = Y > 0 ? Math.sqrt(v) / Y : 1; const t = Math.log10(Math.max(rel, 1e-3)) / 3 + 1;
      [r, g, b] = viridis(t);
    }
    const o = OV ? OV[i] : 0;
    if (ovc && (o & 1)){ r = 255; g = 0; b = 0; }
    if (ovg && (o & 2)){ r = 255; g = 0; b = 255; }
    if (ovd && (o & 4)){ r = 0; g = 64; b = 255; }
    px[4*i] = r; px[4*i+1] = g; px[4*i+2] = b; px[4*i+3] = 255;
  }
  ctx.putImageData(im, 0, 0);
  drawLegend(mode);
}
function drawLegend(mode){
  const c = document.getElementById("legend"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height); g.fillStyle = "#eee"; g.font = "12px sans-serif";
  if (mode === "tone"){ g.fillText("tone-mapped from linear radiance; exposure x 2^EV, sRGB-encoded", 4, 16); return; }
  for (let x = 0; x < 400; x++){ const [r, gg, b] = viridis(x / 399); g.fillStyle = `rgb(${r},${gg},${b})`; g.fillRect(10 + x, 4, 1, 20); }
  g.fillStyle = "#eee";
  if (mode === "false"){
    const unit = D.absolute ? "cd/m²" : "relative luminance (179 Y)";
    const lb = Math.log10(lumBottom), lt = Math.log10(lumTop);
    for (let d = Math.ceil(lb); d <= Math.floor(lt); d++){ const x = 10 + 399 * (d - lb) / (lt - lb); g.fillRect(x, 24, 1, 5); g.fillText("1e" + d, x - 8, 40); }
    g.fillText("luminance, " + unit + ", log scale", 10, 54);
  } else {
    ["0.1 %", "1 %", "10 %", "100 %"].forEach((s, j) => { const x = 10 + 399 * j / 3; g.fillRect(x, 24, 1, 5); g.fillText(s, x - 8, 40); });
    g.fillText("relative standard deviation σ/μ of the luminance, log scale", 10, 54);
  }
}
function readout(x, y){
  if (x < 0 || y < 0 || x >= W || y >= H) return;
  cursor = [x, y]; const i = y * W + x;
  const L = lumAt(RGB, i), unit = D.absolute ? "cd/m²" : "(relative, 179 Y)";
  let s = `pixel x ${x * D.factor}..${(x+1) * D.factor - 1}, y ${y * D.factor}..${(y+1) * D.factor - 1} of ${D.full[0]}x${D.full[1]}` +
          (D.factor > 1 ? ` (mean of a ${D.factor}x${D.factor} block)` : "") + "\n";
  s += `linear RGB ${RGB[3*i].toPrecision(5)} ${RGB[3*i+1].toPrecision(5)} ${RGB[3*i+2].toPrecision(5)}\n`;
  s += `luminance <span id="lum">${L.toPrecision(5)}</span> ${unit}`;
  if (VAR){ s += `\nstandard deviation <span id="lumsd">${(179 * Math.sqrt(VAR[i])).toPrecision(3)}</span> ${unit}`; }
  document.getElementById("readout").innerHTML = s;
}
img.addEventListener("mousemove", e => { const r = img.getBoundingClientRect();
  readout(Math.floor((e.clientX - r.left) * W / r.width), Math.floor((e.clientY - r.top) * H / r.height)); });
img.addEventListener("keydown", e => { const c = cursor || [Math.floor(W/2), Math.floor(H/2)];
  const d = {ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1]}[e.key];
  if (d){ e.preventDefault(); readout(Math.min(W-1, Math.max(0, c[0] + d[0])), Math.min(H-1, Math.max(0, c[1] + d[1]))); } });
function drawCurves(){
  const box = document.getElementById("curvesBox");
  if (!D.curves){ box.style.display = "none"; return; }
  const c = document.getElementById("curves"), g = c.getContext("2d"), cv = D.curves;
  let lo = Infinity, hi = -Infinity; cv.forEach(r => r.forEach(v => { if (isFinite(v)){ lo = Math.min(lo, v); hi = Math.max(hi, v); } }));
  const X = z => 50 + 360 * z / 255, Y = v => 260 - 240 * (v - lo) / (hi - lo || 1);
  g.strokeStyle = "#888"; g.strokeRect(50, 20, 360, 240); g.fillStyle = "#eee"; g.font = "12px sans-serif";
  g.fillText("code z (0..255)", 190, 292); g.save(); g.translate(14, 200); g.rotate(-Math.PI/2); g.fillText("g(z) = ln f⁻¹(z)", 0, 0); g.restore();
  g.fillText(lo.toFixed(1), 14, 262); g.fillText(hi.toFixed(1), 14, 26); g.fillText("0", 46, 276); g.fillText("255", 396, 276);
  ["#e44", "#4c4", "#48f"].forEach((col, ch) => { g.strokeStyle = col; g.beginPath();
    cv.forEach((r, z) => { if (z === 0) g.moveTo(X(z), Y(r[ch])); else g.lineTo(X(z), Y(r[ch])); }); g.stroke(); });
}
function fillSummary(){
  const t = document.getElementById("summary");
  Object.entries(D.summary).forEach(([k, v]) => { const tr = t.insertRow(); tr.insertCell().textContent = k; tr.insertCell().textContent = v; });
  const tr = t.insertRow(); tr.insertCell().textContent = "page data";
  tr.insertCell().textContent = `${W}x${H} (reduced ${D.factor}x from ${D.full[0]}x${D.full[1]}), half floats`;
}
(async () => {
  RGB = await halves(D.rgb); for (let i = 0; i < RGB.length; i++) RGB[i] /= D.scale;
  if (D["var"]){ VAR = await halves(D["var"]); for (let i = 0; i < VAR.length; i++){ const sd = VAR[i] / D.varscale; VAR[i] = sd * sd; } } else { document.getElementById("uncLabel").style.display = "none"; }
  OV = await inflate(D.overlays);
  const ls = []; for (let i = 0; i < W * H; i += Math.max(1, Math.floor(W * H / 200000))) { const L = lumAt(RGB, i); if (L > 0) ls.push(L); }
  ls.sort((a, b) => a - b);
  if (ls.length){
    lumTop = ls[Math.min(ls.length - 1, Math.floor(0.999 * ls.length))]; lumBottom = lumTop / 1e4;
    // the initial exposure puts the log-average luminance at Reinhard's key 0.18
    const logAvg = Math.exp(ls.reduce((a, v) => a + Math.log(v / 179), 0) / ls.length);
    const ev0 = Math.round(4 * Math.log2(0.18 / logAvg)) / 4, s = document.getElementById("ev");
    s.min = ev0 - 12; s.max = ev0 + 12; s.value = ev0;
  }
  document.querySelectorAll("input,select").forEach(el => el.addEventListener("input", draw));
  document.querySelectorAll("input,select").forEach(el => el.addEventListener("change", draw));
  fillSummary(); drawCurves(); draw();
  document.body.dataset.ready = "1";
})();
</script></body></html>
"""
