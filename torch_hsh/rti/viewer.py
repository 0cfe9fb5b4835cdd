r"""A self-contained HTML relighting viewer of a photometric-stereo result (WebGL2).

:func:`write_viewer` writes one HTML file with no network access: the per-pixel normals, the
isotropic Helmholtz coefficient maps, the albedo, the confidence and the residual map are
quantised to 16 bits, deflate-compressed and embedded (base64); the page inflates them with the
browser's ``DecompressionStream`` and uploads them as an ``RGBA16UI`` texture array. A WebGL2
fragment shader evaluates, per pixel, ``I(l) = max(0, sum_k a_k B_k(l, v, n) max(0, n . l))``
with this library's isotropic Helmholtz basis ``B_k`` (the GLSL is generated from the same
recurrence constants as :func:`torch_hsh.helmholtz_isotropic_world`, see
:func:`glsl_isotropic_basis`), ``v = (0, 0, 1)``, and shows ``sRGB(min(1, exposure * I))`` -- the
image :func:`torch_hsh.rti.io.srgb_encode` of ``exposure * HSHResult.relight(l)``.

The page shows the result's name, a help line, the image fitted to the window (a dark neutral
background; the controls in a side panel, below the image in a portrait window, hidden in a window
under 260 x 200 where all of it is image) and a light-direction disc. Drag on the image or the disc to
move the light (``x`` right, ``y`` up, ``z`` toward the viewer; the disc's dot shows it); scroll or
``+``/``-`` to zoom about the cursor; shift-drag or middle-drag pans (the switch OpenLIME uses between
light and pan; "Pan mode" or ``p`` makes a plain drag pan); Fit or ``0`` resets the view. Zoom and pan
only move the canvas (a CSS transform, its pixels unchanged; ``data-view="s,tx,ty"`` on it); buttons
switch to the normal map, the albedo, the confidence and the residual map. The page reads
``#light=x,y,z&mode=relit|normals|albedo|confidence|error&zoom=Z&center=X,Y`` from its URL (zoom
relative to the fit, centre in image pixels from the top left; used by the tests, which screenshot it
in headless Chromium).

When the first frame is drawn (and the GPU has finished it), the page records its times in
milliseconds after the navigation start (``performance.now()``) on ``document.body``:
``data-script-ms`` (the HTML with its embedded data parsed, the script starts),
``data-decoded-ms`` (the coefficient planes inflated) and ``data-first-frame-ms``, with
``data-time-origin`` (``performance.timeOrigin``, ms since the epoch), and logs them in one
``console.info`` line (``benchmarks/bench_viewer.py`` reads it to time the first frame).

Example:
    >>> from torch_hsh.rti.viewer import write_viewer  # doctest: +SKIP
    >>> write_viewer("result.html", HSHResult.read("results/capture/result.npz"))  # doctest: +SKIP
"""
from __future__ import annotations

import base64
import json
import math
import re
import zlib
from html import escape as html_escape
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch

from .._atomic import atomic_file
from .._checks import check_shape

__all__ = ["glsl_isotropic_basis", "write_viewer", "default_exposure", "MODES"]

MODES = ("relit", "normals", "albedo", "confidence", "error")


def _basis_program(order: int) -> List[str]:
    """Straight-line statements ``name = expr`` computing ``B0 .. B{K-1}`` from zi, zo, a, rho, sio."""
    from ..kernel import _iso_gather, _polar_consts

    diag, alpha, beta, col = _polar_consts(order)
    i1, j1, i2, j2, qcol, g_scale = _iso_gather(order)
    L = len(col)
    P = order
    st: List[str] = []
    for side, z in (("Ri", "zi"), ("Ro", "zo")):
        st.append(f"t{side} = 2.0 * {z} - 1.0")
        offs = []
        off = 0
        for j in range(P + 1):
            offs.append(off)
            off += P + 1 - j
        for m in range(P + 1):
            st.append(f"{side}{offs[0] + m} = {diag[m]!r}")
        for j in range(1, P + 1):
            for m in range(P + 1 - j):
                c = offs[j] + m
                prev1 = f"{side}{offs[j - 1] + m}"
                if j == 1:
                    st.append(f"{side}{c} = ({alpha[0][m]!r}) * t{side} * {prev1}")
                else:
                    prev2 = f"{side}{offs[j - 2] + m}"
                    st.append(f"{side}{c} = ({alpha[j - 1][m]!r}) * t{side} * {prev1} - ({beta[j - 1][m]!r}) * {prev2}")
    st.append("G0 = 1.0")
    if P >= 1:
        st.append("a1 = sio * a")
        st.append("r1 = sio * sio * rho")
        st.append("G1 = a1")
        for q in range(2, P + 1):
            st.append(f"G{q} = 2.0 * a1 * G{q - 1} - r1 * G{q - 2}")
    for c in range(L):
        st.append(f"Rg{c} = Ro{c} * G{qcol[c]} * {g_scale[qcol[c]]!r}")
    inv = 1.0 / math.sqrt(2.0)

    def X(i):
        return "0.0" if i == L else f"Ri{i}"

    def Y(j):
        return f"(Rg{j} * {inv!r})" if j < L else f"Rg{j - L}"

    for k in range(len(i1)):
        st.append(f"B{k} = {X(i1[k])} * {Y(j1[k])} + {X(i2[k])} * {Y(j2[k])}")
    return st


def glsl_isotropic_basis(order: int) -> str:
    """GLSL function ``void hbasis(float zi, float zo, float a, float rho, float sio, out float B[K])``.

    ``zi = n . l``, ``zo = n . v`` (clamped to ``[0, 1]``), ``a = l . v - zi zo``,
    ``rho = (1 - zi^2)(1 - zo^2)``, ``sio = sqrt(zi / (1 + zi)) sqrt(zo / (1 + zo))``: the
    arguments of the isotropic kernel of :mod:`torch_hsh.kernel`; ``K = (P+1)(P+2)(P+3)/6``.

    Example:
        >>> "void hbasis" in glsl_isotropic_basis(2)
        True
    """
    K = (order + 1) * (order + 2) * (order + 3) // 6
    lines = [f"void hbasis(float zi, float zo, float a, float rho, float sio, out float B[{K}]) {{"]
    declared = set()
    for s in _basis_program(order):
        name, expr = s.split(" = ", 1)
        if name.startswith("B") and name[1:].isdigit():
            lines.append(f"  B[{name[1:]}] = {_glsl_expr(expr)};")
        else:
            decl = "" if name in declared else "float "
            declared.add(name)
            lines.append(f"  {decl}{name} = {_glsl_expr(expr)};")
    lines.append("}")
    return "\n".join(lines)


def _glsl_expr(expr: str) -> str:
    """Python float reprs (``1.5``, ``2.0``, ``1e-05``) are valid GLSL float literals as they are."""
    return expr


def _eval_program(order: int, zi, zo, a, rho, sio) -> np.ndarray:
    """The generated program evaluated in NumPy (tests: it must equal the library's basis)."""
    env = {"zi": zi, "zo": zo, "a": a, "rho": rho, "sio": sio}
    for s in _basis_program(order):
        name, expr = s.split(" = ", 1)
        env[name] = eval(expr, {}, env)  # noqa: S307 - our own generated arithmetic
    K = (order + 1) * (order + 2) * (order + 3) // 6
    return np.stack([np.broadcast_to(env[f"B{k}"], np.shape(zi)) for k in range(K)], axis=-1)


def default_exposure(result) -> float:
    """``0.8 / (99.5th percentile of the head-on relit image inside the mask)`` (as ``torch-hsh rti``)."""
    m = result.mask.bool()
    head = result.relight(torch.tensor([[0.0, 0.0, 1.0]], dtype=result.normals.dtype))[0][m]
    ref = float(torch.quantile(head.reshape(-1).float(), 0.995)) if head.numel() else 1.0
    return 0.8 / ref if ref > 0 else 1.0


def _pack(channels: np.ndarray, mask: np.ndarray):
    """(H, W, N) float -> uint16 codes per channel (lo, span over the mask) and the per-channel lo/span."""
    v = channels[mask]
    lo = v.min(axis=0) if v.size else np.zeros(channels.shape[-1])
    span = (v.max(axis=0) - lo) if v.size else np.ones(channels.shape[-1])
    span = np.where(span > 0, span, 1.0)
    q = np.rint(np.clip((channels - lo) / span, 0, 1) * 65535).astype(np.uint16)
    q[~mask] = 0
    return q, lo, span


def write_viewer(path, result, exposure: Optional[float] = None, title: str = "torch_hsh result",
                 overwrite: bool = False, max_bytes: Optional[int] = 30 * 2 ** 20) -> float:
    r"""Write the relighting viewer of an :class:`~torch_hsh.ps.HSHResult` as one HTML file.

    Args:
        path: target ``.html`` file (refused if it exists unless ``overwrite``).
        result: an ``HSHResult`` over an ``(H, W)`` image (3 colour channels).
        exposure: factor on the radiance before the sRGB curve (default
            :func:`default_exposure`).
        title: page title.
        max_bytes: refuse to write a larger file (default 30 MiB); ``None``: no limit.

    Returns:
        The exposure used (the page shows ``sRGB(min(1, exposure * relight(l)))``).

    Example:
        >>> write_viewer("cat.html", HSHResult.read("results/cat/result.npz"))  # doctest: +SKIP
        1.73
    """
    p = Path(path)
    if p.exists() and not overwrite:
        raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
    n = result.normals.detach().cpu().double()
    a = result.coefficients.detach().cpu().double()
    # the viewer shows an (H, W) image of an RGB result
    sizes = check_shape(n, "result.normals", ("H", "W", 3))
    check_shape(a, "result.coefficients", ("H", "W", 3, "K"), sizes=sizes)
    H, W, C, K = a.shape
    from ..render.images import order_from_num_functions

    order = order_from_num_functions(K)
    mask = result.mask.detach().cpu().bool().numpy()
    if exposure is None:
        exposure = default_exposure(result)
    albedo = result.albedo.detach().cpu().double().numpy() if result.albedo is not None else np.zeros((H, W, 3))
    conf = (result.confidence.detach().cpu().double().numpy() if getattr(result, "confidence", None) is not None
            else np.ones((H, W)))
    resid = result.residual.detach().cpu().double().numpy()
    chans = np.concatenate([a.reshape(H, W, 3 * K).numpy(), (n.numpy() + 1) / 2, albedo, conf[..., None],
                            resid[..., None], mask[..., None].astype(np.float64)], axis=-1)
    nl = -(-chans.shape[-1] // 4)
    chans = np.concatenate([chans, np.zeros((H, W, 4 * nl - chans.shape[-1]))], axis=-1)
    q, lo, span = _pack(chans, mask)
    lo[3 * K + 8], span[3 * K + 8] = 0.0, 1.0  # the mask channel: 0 outside, 1 inside
    q[..., 3 * K + 8] = np.where(mask, 65535, 0)
    # layer-major RGBA16UI texture array, rows bottom-up (WebGL's texture origin is the lower left)
    layers = q.reshape(H, W, nl, 4)[::-1].transpose(2, 0, 1, 3)
    blob = base64.b64encode(zlib.compress(np.ascontiguousarray(layers).astype("<u2").tobytes(), 6)).decode("ascii")
    rmax = float(resid[mask].max()) if mask.any() else 1.0
    meta = {"width": W, "height": H, "layers": nl, "K": K, "order": order, "exposure": float(exposure),
            "lo": [float(v) for v in lo], "span": [float(v) for v in span], "residual_max": rmax or 1.0}
    # the heading: the result's name, after a muted "torch_hsh" when the title is "torch_hsh: NAME" (the CLI's)
    brand, sep, name = title.partition(": ")
    heading = (f'<span class="brand">{html_escape(brand)}</span>{html_escape(name)}' if sep and brand == "torch_hsh"
               else html_escape(title))
    fields = {"__TITLE__": html_escape(title), "__HEADING__": heading, "__META__": json.dumps(meta), "__DATA__": blob,
              "__BASIS__": glsl_isotropic_basis(order), "__K__": str(K), "__NL__": str(nl), "__NCH__": str(4 * nl)}
    # one pass: a title holding a placeholder's name stays as it is
    html = re.sub("|".join(fields), lambda m: fields[m.group(0)], _TEMPLATE)
    data = html.encode("utf-8")
    if max_bytes is not None and len(data) > max_bytes:
        raise ValueError(f"the viewer would be {len(data) / 2 ** 20:.1f} MiB, more than {max_bytes / 2 ** 20:.0f} MiB")
    with atomic_file(p) as tmp:
        tmp.write_bytes(data)
    return float(exposure)


_TEMPLATE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>__TITLE__</title>
<style>
:root{--bg:#17181b;--panel:#1f2024;--line:#2e3036;--text:#e8e8ea;--muted:#9b9ea6;--accent:#f5b942;--btn:#2a2c31;--btnh:#34373d}
*{box-sizing:border-box}
html,body{height:100%}
body{margin:0;background:var(--bg);color:var(--text);font:13px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,sans-serif;
  display:grid;grid-template:"top top" auto "view panel" minmax(0,1fr)/minmax(0,1fr) 208px;overflow:hidden}
header{grid-area:top;display:flex;align-items:baseline;gap:14px;padding:9px 16px;border-bottom:1px solid var(--line);min-width:0}
h1{margin:0;font-size:16px;font-weight:600;white-space:nowrap;overflow:hidden;text-overflow:ellipsis;flex:0 1 auto}
h1 .brand{color:var(--muted);font-weight:400;margin-right:6px}
#help{margin:0;color:var(--muted);font-size:12.5px;flex:1 1 0;min-width:0;white-space:nowrap;overflow:hidden;text-overflow:ellipsis}
#help b{color:var(--text);font-weight:500}
#view{grid-area:view;position:relative;overflow:hidden;background:#101113;cursor:crosshair;touch-action:none;user-select:none}
#view.pan,#view.panning{cursor:grab}#view.panning{cursor:grabbing}
canvas{position:absolute;left:0;top:0;transform-origin:0 0;display:block}
canvas.px{image-rendering:pixelated}
aside{grid-area:panel;background:var(--panel);border-left:1px solid var(--line);padding:12px 14px;display:flex;flex-direction:column;gap:14px;overflow:auto}
aside section{display:flex;flex-direction:column;gap:7px}
h2{margin:0;font-size:11px;font-weight:600;letter-spacing:.08em;text-transform:uppercase;color:var(--muted)}
#lightpad{width:128px;height:128px;align-self:center;cursor:crosshair;touch-action:none;display:block}
#lightval{color:var(--muted);font-variant-numeric:tabular-nums;text-align:center;font-size:12px}
.row{display:flex;gap:6px;align-items:center}
button{font:inherit;color:var(--text);background:var(--btn);border:1px solid var(--line);border-radius:6px;padding:4px 10px;cursor:pointer;min-height:28px}
button:hover{background:var(--btnh)}button:focus-visible{outline:2px solid var(--accent);outline-offset:1px}
button[aria-pressed="true"]{background:#3b3422;border-color:var(--accent);color:#ffe1a3}
#zout,#zin{width:30px;padding:0;font-size:16px;line-height:1}
#zoomval{min-width:46px;text-align:center;font-variant-numeric:tabular-nums;color:var(--muted)}
#modes{display:flex;flex-wrap:wrap;gap:6px}#modes button{padding:4px 8px}
#info{color:var(--muted);font-size:11.5px;margin-top:auto}
@media (max-width:760px),(max-height:520px){
  body{grid-template-columns:minmax(0,1fr) 152px}
  header{padding:6px 12px;gap:10px}h1{font-size:14px}
  #help{white-space:normal;font-size:11.5px;line-height:1.3}
  aside{padding:8px 10px;gap:8px}aside h2{display:none}
  #lightpad{width:84px;height:84px}#lightval{display:none}
  #modes{gap:4px}aside button{min-height:24px;padding:2px 7px;font-size:12px}#zout,#zin{width:26px}
  #info{display:none}
}
@media (max-aspect-ratio:4/5){
  body{grid-template:"top" auto "view" minmax(0,1fr) "panel" auto/minmax(0,1fr)}
  header{flex-direction:column;gap:2px}#help{flex:none}
  aside{border-left:0;border-top:1px solid var(--line);flex-direction:row;flex-wrap:wrap;align-items:center;gap:8px 14px}
  #lightpad{width:72px;height:72px}#lightval{display:none}
}
@media (max-width:260px),(max-height:200px){
  body{grid-template:"view" minmax(0,1fr)/minmax(0,1fr)}
  header,aside{display:none}
}
</style></head>
<body>
<header><h1 id="title">__HEADING__</h1>
<p id="help"><b>Drag</b> on the image or the disc to move the light &middot; <b>scroll</b> or <b>+</b>/<b>&minus;</b> to zoom &middot;
<b>shift-drag</b> or middle-drag to pan (as OpenLIME) &middot; <b>Fit</b> or <b>0</b> resets the view</p></header>
<main id="view"><canvas id="c" aria-label="relit image"></canvas></main>
<aside>
<section><h2>Light</h2>
<svg id="lightpad" viewBox="-1.12 -1.12 2.24 2.24" role="slider" aria-label="light direction: click or drag">
<defs><radialGradient id="shade" cx="0" cy="0" r="1.25" fx="0" fy="0" gradientUnits="userSpaceOnUse">
<stop offset="0" stop-color="#d9d3c4"/><stop offset=".55" stop-color="#6d6a63"/><stop offset="1" stop-color="#1c1c1e"/></radialGradient></defs>
<circle r="1" fill="url(#shade)" stroke="#4a4c52" stroke-width=".02"/>
<g fill="none" stroke="#000" stroke-opacity=".28" stroke-width=".012"><circle r=".866"/><circle r=".5"/>
<path d="M-1 0H1M0 -1V1"/></g>
<circle id="lightdot" r=".085" fill="var(--accent)" stroke="#fff" stroke-width=".03"/></svg>
<div id="lightval"></div></section>
<section><h2>View</h2>
<div class="row"><button id="zout" title="zoom out (-)">&minus;</button><span id="zoomval">100%</span>
<button id="zin" title="zoom in (+)">+</button><button id="fit" title="fit the image to the window (0 or double-click)">Fit</button></div>
<div class="row"><button id="pan" aria-pressed="false" title="drag pans instead of moving the light (p)">Pan mode</button></div></section>
<section><h2>Show</h2><div id="modes">
<button data-m="relit">Relit</button><button data-m="normals">Normals</button><button data-m="albedo">Albedo</button>
<button data-m="confidence">Confidence</button><button data-m="error">Residual</button></div></section>
<div id="info"></div>
</aside>
<script id="meta" type="application/json">__META__</script>
<script id="data" type="application/octet-stream">__DATA__</script>
<script>
"use strict";
const T_SCRIPT = performance.now();  // the HTML, embedded data included, is parsed up to here
const META = JSON.parse(document.getElementById('meta').textContent);
const MODES = ['relit', 'normals', 'albedo', 'confidence', 'error'];
const state = {light: [0, 0, 1], mode: 0, zoom: 1, cx: META.width / 2, cy: META.height / 2, pan: false};
function parseHash() {
  const h = new URLSearchParams(location.hash.slice(1));
  if (h.get('light')) { const v = h.get('light').split(',').map(Number); const n = Math.hypot(...v); state.light = v.map(x => x / n); }
  if (h.get('mode')) state.mode = Math.max(0, MODES.indexOf(h.get('mode')));
  if (h.get('zoom')) state.zoom = Number(h.get('zoom')) || 1;  // relative to the fit view
  if (h.get('center')) { const c = h.get('center').split(',').map(Number); if (c.length === 2 && c.every(isFinite)) [state.cx, state.cy] = c; }
}
// the view: the image scaled by vt.s (zoom times the scale that fits it in the window), its point
// (state.cx, state.cy) (image pixels from the top left) at the centre of #view; only the canvas's CSS
// transform changes, never its pixels (the rendered image)
const TINY = matchMedia('(max-width:260px),(max-height:200px)');  // no header and no panel: all window is image
const vt = {s: 1, tx: 0, ty: 0, fit: 1};
const ZMIN = 0.5, SMAX = 40;
function clamp(v, a, b) { return Math.min(b, Math.max(a, v)); }
function layout() {
  const view = document.getElementById('view'), cv = document.getElementById('c');
  const vw = view.clientWidth, vh = view.clientHeight, m = TINY.matches ? 0 : 16;
  vt.fit = Math.max(1e-3, Math.min((vw - 2 * m) / META.width, (vh - 2 * m) / META.height));
  state.zoom = clamp(state.zoom, ZMIN, Math.max(1, SMAX / vt.fit));
  state.cx = clamp(state.cx, 0, META.width); state.cy = clamp(state.cy, 0, META.height);
  vt.s = state.zoom * vt.fit; vt.tx = Math.round(vw / 2 - vt.s * state.cx); vt.ty = Math.round(vh / 2 - vt.s * state.cy);
  cv.style.transform = 'translate(' + vt.tx + 'px,' + vt.ty + 'px) scale(' + vt.s + ')';
  cv.classList.toggle('px', vt.s >= 1);  // magnified: sharp image pixels
  document.getElementById('zoomval').textContent = (vt.s >= 10 ? vt.s.toFixed(0) : vt.s.toPrecision(2)).replace(/\.0+$/, '') + '\u00d7';
  // image pixel (i, j) (from the top left) covers [tx + s i, tx + s (i + 1)) x [ty + s j, ...) of #view
  cv.dataset.view = vt.s.toFixed(6) + ',' + vt.tx + ',' + vt.ty;
  view.dataset.size = vw + ',' + vh;
}
function zoomBy(f, mx, my) {  // zoom by f keeping the image point under (mx, my) of #view (default: its centre) in place
  const view = document.getElementById('view'), vw = view.clientWidth, vh = view.clientHeight;
  if (mx === undefined) { mx = vw / 2; my = vh / 2; }
  const px = (mx - vt.tx) / vt.s, py = (my - vt.ty) / vt.s;
  state.zoom = clamp(state.zoom * f, ZMIN, Math.max(1, SMAX / vt.fit));
  const s = state.zoom * vt.fit;
  state.cx = px - (mx - vw / 2) / s; state.cy = py - (my - vh / 2) / s; layout();
}
function fit() { state.zoom = 1; state.cx = META.width / 2; state.cy = META.height / 2; layout(); }
const VS = `#version 300 es
in vec2 p; void main() { gl_Position = vec4(p, 0.0, 1.0); }`;
const FS = `#version 300 es
precision highp float; precision highp int; precision highp usampler2DArray;
uniform usampler2DArray tex; uniform vec3 light; uniform int mode; uniform float exposure;
uniform float lo[__NCH__]; uniform float span[__NCH__]; uniform float rmax;
out vec4 color;
__BASIS__
float ch(uvec4 t[__NL__], int i) { uvec4 v = t[i / 4]; int j = i - 4 * (i / 4);
  uint u = j == 0 ? v.x : (j == 1 ? v.y : (j == 2 ? v.z : v.w)); return lo[i] + span[i] * float(u) / 65535.0; }
vec3 srgb(vec3 x) { x = clamp(x, 0.0, 1.0);
  return mix(12.92 * x, 1.055 * pow(max(x, vec3(0.0031308)), vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x)); }
void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  uvec4 t[__NL__];
  for (int i = 0; i < __NL__; i++) t[i] = texelFetch(tex, ivec3(px, i), 0);
  int K = __K__;
  vec3 n = vec3(ch(t, 3 * K), ch(t, 3 * K + 1), ch(t, 3 * K + 2)) * 2.0 - 1.0;
  if (ch(t, 3 * K + 8) < 0.5 || dot(n, n) < 0.25) { color = vec4(0.0, 0.0, 0.0, 1.0); return; }
  n = normalize(n);
  if (mode == 1) { color = vec4((n + 1.0) * 0.5, 1.0); return; }
  if (mode == 2) { color = vec4(srgb(exposure / 3.14159265 * vec3(ch(t, 3 * K + 3), ch(t, 3 * K + 4), ch(t, 3 * K + 5))), 1.0); return; }
  if (mode == 3) { color = vec4(vec3(ch(t, 3 * K + 6)), 1.0); return; }
  if (mode == 4) { color = vec4(vec3(ch(t, 3 * K + 7) / rmax), 1.0); return; }
  vec3 l = normalize(light);
  float zi = dot(n, l), zo = clamp(n.z, 0.0, 1.0);
  if (zi <= 0.0 || n.z <= 0.0) { color = vec4(srgb(vec3(0.0)), 1.0); return; }
  zi = min(zi, 1.0);
  float a = l.z - zi * zo, rho = (1.0 - zi * zi) * (1.0 - zo * zo);
  float sio = sqrt(zi / (1.0 + zi)) * sqrt(zo / (1.0 + zo));
  float B[__K__]; hbasis(zi, zo, a, rho, sio, B);
  vec3 I = vec3(0.0);
  for (int k = 0; k < __K__; k++) I += B[k] * vec3(ch(t, k), ch(t, K + k), ch(t, 2 * K + k));
  color = vec4(srgb(exposure * max(I * zi, 0.0)), 1.0);
}`;
function shader(gl, type, src) { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s)); return s; }
async function main() {
  parseHash();
  const cv = document.getElementById('c'); cv.width = META.width; cv.height = META.height;
  layout(); window.addEventListener('resize', layout);
  const gl = cv.getContext('webgl2', {preserveDrawingBuffer: true, antialias: false});
  if (!gl) { document.getElementById('info').textContent = 'WebGL2 is not available'; return; }
  const b64 = document.getElementById('data').textContent.trim();
  let raw;
  if (Uint8Array.fromBase64) raw = Uint8Array.fromBase64(b64);  // native (Chromium 140+, Firefox 133+, Safari 18.2+)
  else { const s = atob(b64); raw = new Uint8Array(s.length); for (let i = 0; i < s.length; i++) raw[i] = s.charCodeAt(i); }
  const T_BASE64 = performance.now();
  const buf = await new Response(new Blob([raw]).stream().pipeThrough(new DecompressionStream('deflate'))).arrayBuffer();
  const data = new Uint16Array(buf);
  const T_DECODED = performance.now();
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl, gl.VERTEX_SHADER, VS)); gl.attachShader(prog, shader(gl, gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog); if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  const tex = gl.createTexture(); gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGBA16UI, META.width, META.height, META.layers, 0, gl.RGBA_INTEGER, gl.UNSIGNED_SHORT, data);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST); gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  const vb = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, vb);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
  const loc = gl.getAttribLocation(prog, 'p'); gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
  const U = name => gl.getUniformLocation(prog, name);
  gl.uniform1i(U('tex'), 0); gl.uniform1fv(U('lo'), META.lo); gl.uniform1fv(U('span'), META.span);
  gl.uniform1f(U('exposure'), META.exposure); gl.uniform1f(U('rmax'), META.residual_max);
  const view = document.getElementById('view'), pad = document.getElementById('lightpad');
  const dot = document.getElementById('lightdot'), shade = document.getElementById('shade');
  const modeButtons = document.querySelectorAll('#modes button'), panButton = document.getElementById('pan');
  function showLight() {
    const [x, y, z] = state.light;
    dot.setAttribute('cx', x.toFixed(4)); dot.setAttribute('cy', (-y).toFixed(4));
    shade.setAttribute('fx', (0.9 * x).toFixed(4)); shade.setAttribute('fy', (-0.9 * y).toFixed(4));
    shade.setAttribute('cx', (0.5 * x).toFixed(4)); shade.setAttribute('cy', (-0.5 * y).toFixed(4));
    const el = Math.asin(Math.min(1, Math.max(-1, z))) * 180 / Math.PI, az = Math.atan2(y, x) * 180 / Math.PI;
    document.getElementById('lightval').textContent = 'elevation ' + el.toFixed(0) + '\u00b0 \u00b7 azimuth ' + az.toFixed(0) + '\u00b0';
  }
  function draw() { gl.viewport(0, 0, META.width, META.height); gl.uniform3fv(U('light'), state.light);
    gl.uniform1i(U('mode'), state.mode); gl.drawArrays(gl.TRIANGLES, 0, 3); showLight();
    for (const b of modeButtons) b.setAttribute('aria-pressed', String(b.dataset.m === MODES[state.mode]));
    document.getElementById('info').textContent = MODES[state.mode] + '  light ' + state.light.map(v => v.toFixed(3)).join(', '); }
  // the light from a point of a square-ish region: x right, y up, on the unit disc, z toward the viewer
  function setLight(e, r) { let x = 2 * (e.clientX - r.left) / r.width - 1, y = 1 - 2 * (e.clientY - r.top) / r.height; const d = Math.hypot(x, y);
    if (d > 0.999) { x *= 0.999 / d; y *= 0.999 / d; } state.light = [x, y, Math.sqrt(Math.max(0, 1 - x * x - y * y))]; state.mode = 0; draw(); }
  function imageRect() {  // the part of the image on the screen (all of it at the fit view)
    const c = cv.getBoundingClientRect(), v = view.getBoundingClientRect();
    const l = Math.max(c.left, v.left), t = Math.max(c.top, v.top), r = Math.min(c.right, v.right), b = Math.min(c.bottom, v.bottom);
    return r - l > 4 && b - t > 4 ? {left: l, top: t, width: r - l, height: b - t} : v;
  }
  let drag = null;
  view.addEventListener('pointerdown', e => {
    const pan = state.pan || e.shiftKey || e.button === 1 || e.button === 2;
    if (e.button !== 0 && !pan) return;
    e.preventDefault(); view.setPointerCapture(e.pointerId);
    drag = {pan, x: e.clientX, y: e.clientY, rect: imageRect()};
    if (pan) view.classList.add('panning'); else setLight(e, drag.rect);
  });
  view.addEventListener('pointermove', e => {
    if (!drag) return;
    if (!drag.pan) { setLight(e, drag.rect); return; }
    state.cx -= (e.clientX - drag.x) / vt.s; state.cy -= (e.clientY - drag.y) / vt.s; drag.x = e.clientX; drag.y = e.clientY; layout();
  });
  const endDrag = () => { drag = null; view.classList.remove('panning'); };
  view.addEventListener('pointerup', endDrag); view.addEventListener('pointercancel', endDrag);
  view.addEventListener('contextmenu', e => e.preventDefault());
  view.addEventListener('wheel', e => { e.preventDefault(); const v = view.getBoundingClientRect();
    zoomBy(Math.exp(-e.deltaY * (e.deltaMode ? 0.05 : 0.0015)), e.clientX - v.left, e.clientY - v.top); }, {passive: false});
  pad.addEventListener('pointerdown', e => { e.preventDefault(); pad.setPointerCapture(e.pointerId); setLight(e, padRect()); });
  pad.addEventListener('pointermove', e => { if (e.buttons & 1) setLight(e, padRect()); });
  function padRect() { const r = pad.getBoundingClientRect(), k = 1 / 1.12;  // the unit disc inside the viewBox margin
    return {left: r.left + r.width * (1 - k) / 2, top: r.top + r.height * (1 - k) / 2, width: r.width * k, height: r.height * k}; }
  document.getElementById('zin').onclick = () => zoomBy(1.5);
  document.getElementById('zout').onclick = () => zoomBy(1 / 1.5);
  document.getElementById('fit').onclick = fit;
  const togglePan = () => { state.pan = !state.pan; panButton.setAttribute('aria-pressed', String(state.pan)); view.classList.toggle('pan', state.pan); };
  panButton.onclick = togglePan;
  window.addEventListener('keydown', e => {
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    if (e.key === '+' || e.key === '=') zoomBy(1.5); else if (e.key === '-') zoomBy(1 / 1.5);
    else if (e.key === '0' || e.key === 'f') fit(); else if (e.key === 'p') togglePan(); else return;
    e.preventDefault();
  });
  for (const b of modeButtons) b.onclick = () => { state.mode = MODES.indexOf(b.dataset.m); draw(); };
  window.addEventListener('hashchange', () => { parseHash(); layout(); draw(); });
  draw();
  // first frame: wait for the GPU (a 1-pixel read) and record the times (ms after navigation start)
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  const T_FIRST = performance.now(), ds = document.body.dataset;
  ds.scriptMs = T_SCRIPT.toFixed(1); ds.base64Ms = T_BASE64.toFixed(1); ds.decodedMs = T_DECODED.toFixed(1); ds.firstFrameMs = T_FIRST.toFixed(1);
  ds.timeOrigin = performance.timeOrigin.toFixed(1);
  console.info('torch_hsh viewer: first frame ' + ds.firstFrameMs + ' ms (script ' + ds.scriptMs +
               ' ms, base64 ' + ds.base64Ms + ' ms, decoded ' + ds.decodedMs + ' ms) after navigation start ' + ds.timeOrigin);
  document.title = document.title + ' (ready)';
}
main().catch(e => { document.getElementById('info').textContent = 'error: ' + e.message; console.error(e); });
</script></body></html>
"""
