"""Tests of the relight / OpenLIME export options: the Deep Zoom layouts (tiles read back by a reader written from
the Deep Zoom layout and OpenLIME's tile URLs) and the non-negative projection."""
import json
import math
import re

import numpy as np
import pytest
import torch
from PIL import Image

from torch_hsh.rti.io import deepzoom_levels, save_relight, write_deepzoom


def read_dzi(dzi):
    """(Format, TileSize, Overlap, Width, Height) of a .dzi file."""
    text = dzi.read_text()
    get = {k: re.search(rf'{k}="([^"]+)"', text).group(1) for k in ("Format", "TileSize", "Overlap", "Width", "Height")}
    return get["Format"], int(get["TileSize"]), int(get["Overlap"]), int(get["Width"]), int(get["Height"])


def assemble(files, level, w, h, fmt, tile, overlap):
    """One level of a pyramid put back together from its tiles; checks every tile's size and that the overlapping
    pixels agree (exactly for PNG) with the neighbour's."""
    out = np.full((h, w, 3), -1, np.int32)
    ncol, nrow = -(-w // tile), -(-h // tile)
    names = {p.name for p in (files / str(level)).iterdir()}
    assert names == {f"{c}_{r}.{fmt}" for c in range(ncol) for r in range(nrow)}
    for r in range(nrow):
        for c in range(ncol):
            t = np.asarray(Image.open(files / str(level) / f"{c}_{r}.{fmt}").convert("RGB")).astype(np.int32)
            x0, y0 = max(0, c * tile - overlap), max(0, r * tile - overlap)
            x1, y1 = min(w, (c + 1) * tile + overlap), min(h, (r + 1) * tile + overlap)
            assert t.shape == (y1 - y0, x1 - x0, 3), (level, c, r, t.shape)
            region = out[y0:y1, x0:x1]
            seen = region >= 0
            if fmt == "png":
                assert (region[seen] == t[seen]).all(), f"overlap of tile {c}_{r} of level {level} disagrees"
            region[~seen] = t[~seen]
    assert (out >= 0).all()
    return out


def _image(h, w, seed=0):
    g = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    smooth = 127 + 100 * np.sin(x[..., None] / 23.0 + np.arange(3)) * np.cos(y[..., None] / 17.0)
    return np.clip(smooth + g.normal(0, 6, (h, w, 3)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("layout", ["deepzoom", "deepzoom1px"])
@pytest.mark.parametrize("h, w", [(300, 600), (509, 260), (254, 255)])
def test_deepzoom_tiles_reassemble_to_the_image(tmp_path, layout, h, w):
    img = _image(h, w)
    dzi = write_deepzoom(tmp_path / "p", img, fmt="png", layout=layout)
    fmt, tile, overlap, W, H = read_dzi(dzi)
    assert (fmt, tile, overlap, W, H) == ("png", 254, 1, w, h)
    files = tmp_path / "p_files"
    sizes = deepzoom_levels(w, h, layout=layout)
    assert sorted(int(p.name) for p in files.iterdir()) == list(range(len(sizes)))
    top = (max(w, h) - 1).bit_length()
    if layout == "deepzoom1px":
        assert sizes[0] == (1, 1) and len(sizes) == top + 1  # every level of the Deep Zoom specification
    else:  # folder 0 fits one tile; as many folders as OpenLIME's deepzoom layout fetches
        assert max(sizes[0]) <= tile and (len(sizes) == 1 or max(sizes[1]) > tile)
        assert len(sizes) == max(1, math.ceil(math.log2(max(w, h) / tile)) + 1)
    ref = img.astype(np.int32)
    for k in range(len(sizes) - 1, -1, -1):
        lw, lh = sizes[k]
        assert (lw, lh) == (-(-w // 2 ** (len(sizes) - 1 - k)), -(-h // 2 ** (len(sizes) - 1 - k)))
        got = assemble(files, k, lw, lh, "png", tile, overlap)
        assert (got == ref).all(), f"level {k}"
        a = np.pad(ref, ((0, lh % 2), (0, lw % 2), (0, 0)), mode="edge")
        ref = (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2] + 2) // 4


def test_relight_deepzoom_matches_the_image_layout(tmp_path):
    g = torch.Generator().manual_seed(0)
    c = torch.randn(270, 300, 3, 9, generator=g, dtype=torch.float64)
    c = c + torch.linspace(-1, 1, 300, dtype=torch.float64)[None, :, None, None]  # structure, so JPEG keeps it
    for fmt in ("png", "jpg"):
        flat = save_relight(tmp_path / f"image_{fmt}", c, fmt=fmt)
        tiled = save_relight(tmp_path / f"dz_{fmt}", c, fmt=fmt, layout="deepzoom")
        assert json.loads((flat / "info.json").read_text()) == json.loads((tiled / "info.json").read_text())
        for j in range(9):
            fmt_, tile, overlap, W, H = read_dzi(tiled / f"plane_{j}.dzi")
            assert (fmt_, W, H) == (fmt, 300, 270)
            levels = deepzoom_levels(W, H)
            assert len(levels) == 2
            got = assemble(tiled / f"plane_{j}_files", 1, W, H, fmt, tile, overlap)
            want = np.asarray(Image.open(flat / f"plane_{j}.{fmt}").convert("RGB")).astype(np.int32)
            if fmt == "png":
                assert (got == want).all()
            else:  # each tile is its own JPEG: within the JPEG error of either
                assert np.sqrt(((got - want) ** 2).mean()) < 3.0 and np.abs(got - want).mean() < 2.0
    with pytest.raises(ValueError, match="layout"):
        save_relight(tmp_path / "bad", c, layout="tiles")


def test_deepzoom_overwrite_removes_stale_tiles(tmp_path):
    write_deepzoom(tmp_path / "p", _image(600, 600), fmt="png")
    write_deepzoom(tmp_path / "p", _image(100, 100), fmt="png")
    assert sorted(p.name for p in (tmp_path / "p_files").iterdir()) == ["0"]


# --------------------------------------------------------------------------- #
# non-negative export
# --------------------------------------------------------------------------- #
def _dense_cap(max_deg, nt=120, nphi=480):
    """A test grid of the cap, independent of the solver's: uniform in theta and phi, offset from its rings."""
    t = np.radians(max_deg) * (np.arange(nt) + 0.37) / nt
    t = np.concatenate([t, [np.radians(max_deg)]])
    ph = 2 * np.pi * (np.arange(nphi) + 0.21) / nphi
    T, P = np.meshgrid(t, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    return torch.tensor(d, dtype=torch.float64)


def _negative_scene():
    from torch_hsh.render import scenes

    n, m = scenes.sphere_normals(20, radius=0.9, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    a = torch.zeros(20, 20, 3, 4, dtype=torch.float64)
    a[..., 0] = 0.3 + 1.5 * torch.rand(20, 20, 3, generator=g, dtype=torch.float64)
    a[..., 1:] = 0.6 * torch.rand(20, 20, 3, 3, generator=g, dtype=torch.float64)  # glossy: lobes the cap fit rings
    return n, m, a


@pytest.mark.parametrize("terms", [9, 16])
def test_nonnegative_rti_sum_is_nonnegative_and_feasible_pixels_unchanged(terms):
    from torch_hsh.rti import OPENLIME_THETA_CLAMP, evaluate_rti, nonnegative_rti, project_to_rti

    n, m, a = _negative_scene()
    c0 = project_to_rti(n, a, terms, mask=m, exposure=0.8, max_angle_deg=50.0, nz=12, nphi=24)
    c1 = project_to_rti(n, a, terms, mask=m, exposure=0.8, max_angle_deg=50.0, nz=12, nphi=24, nonnegative=True)
    dense = _dense_cap(math.degrees(OPENLIME_THETA_CLAMP))
    v0 = evaluate_rti(c0, dense)  # (K, H, W, 3)
    v1 = evaluate_rti(c1, dense)
    neg = (v0 < 0).any(0)
    assert neg[m].float().mean() > 0.05, "the fixture must have negative sums to remove"
    assert float(v1.min()) > -1e-3  # non-negative to rounding (half a code is 2e-3) on a grid the solver never saw
    changed = (c1 != c0).any(-1)
    assert not changed[~neg].any()  # pixels and colours already non-negative everywhere are unchanged...
    assert changed[neg].float().mean() > 0.9  # ...the others moved
    assert (c1[~m] == 0).all()
    # beyond the clamp a viewer evaluates at the clamp: the sum is non-negative at every light of the hemisphere
    grazing = torch.tensor([[math.cos(p), math.sin(p), 0.01] for p in np.linspace(0, 2 * np.pi, 50)], dtype=torch.float64)
    assert float(evaluate_rti(c1, grazing, OPENLIME_THETA_CLAMP).min()) > -1e-3
    # the constrained fit is the nearest: it moves the function less than the constant shift that also removes it
    shift = c0.clone()
    shift[..., 0] = shift[..., 0] + (-v0.amin(0)).clamp(min=0) * math.sqrt(2 * math.pi)
    inside = _dense_cap(50.0, 30, 120)
    err = lambda c: float((evaluate_rti(c, inside) - evaluate_rti(c0, inside))[:, m].pow(2).mean())  # noqa: E731
    assert err(c1) < 0.5 * err(shift)
    # the library call on the coefficients gives the same as the option (identity metric: hemisphere projection)
    h0 = project_to_rti(n, a, terms, mask=m, exposure=0.8, nz=12, nphi=24)
    h1 = project_to_rti(n, a, terms, mask=m, exposure=0.8, nz=12, nphi=24, nonnegative=True)
    assert torch.allclose(nonnegative_rti(h0), h1, atol=1e-12)


def test_nonnegative_rti_margin_and_arguments():
    from torch_hsh.rti import evaluate_rti, nonnegative_rti

    c = torch.zeros(5, 3, 9, dtype=torch.float64)
    c[..., 0] = 0.4
    c[..., 1] = torch.linspace(0, 1.5, 5, dtype=torch.float64)[:, None]
    got = nonnegative_rti(c, margin=0.01)
    dense = _dense_cap(81.0, 40, 160)
    assert float(evaluate_rti(got, dense).min()) >= 0.01 - 1e-3
    assert (got[0] == c[0]).all()  # a constant 0.4 / sqrt(2 pi) meets the margin
    with pytest.raises(ValueError, match="max_angle_deg"):
        nonnegative_rti(c, max_angle_deg=0)
    with pytest.raises(ValueError, match="metric"):
        nonnegative_rti(c, metric=torch.eye(4, dtype=torch.float64))


# --------------------------------------------------------------------------- #
# the real viewer: OpenLIME in headless Chromium (skipped where either is missing)
# --------------------------------------------------------------------------- #
def _openlime_js():
    import os
    from pathlib import Path

    env = os.environ.get("TORCH_HSH_OPENLIME")  # a folder holding openlime.min.js
    here = Path(__file__).resolve()
    for d in ([Path(env)] if env else []) + [p / "shared" / "tools" / "openlime" for p in here.parents[1:3]]:
        if (d / "openlime.min.js").is_file():
            return d / "openlime.min.js"
    return None


_PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8">
<style>html,body{margin:0;padding:0;background:#000;overflow:hidden} .openlime{width:100vw;height:100vh}</style>
<script src="openlime.min.js"></script></head><body><div class="openlime"></div><script>
const q = new URLSearchParams(location.search);
const lime = new OpenLIME.Viewer('.openlime', {background: [0, 0, 0, 1]});
const layer = new OpenLIME.Layer({type: 'rti', layout: q.get('layout'), url: q.get('dir') + '/info.json'});
lime.addLayer('rti', layer);
const l = q.get('light').split(',').map(Number);
layer.setLight([l[0], l[1]], 0);
</script></body></html>
"""


def test_openlime_draws_the_deepzoom_folder_like_the_image_folder(tmp_path):
    import functools
    import http.server
    import shutil
    import subprocess
    import threading

    chromium = next((shutil.which(c) for c in ("chromium", "chromium-browser", "google-chrome") if shutil.which(c)),
                    None)
    js = _openlime_js()
    if chromium is None or js is None:
        pytest.skip("needs Chromium (apt-get install chromium) and an OpenLIME build (openlime.min.js in "
                    "$TORCH_HSH_OPENLIME or ../shared/tools/openlime)")
    shutil.copy(js, tmp_path / "openlime.min.js")
    (tmp_path / "page.html").write_text(_PAGE, encoding="utf-8")
    y, x = torch.meshgrid(torch.linspace(-1, 1, 270, dtype=torch.float64),
                          torch.linspace(-1, 1, 300, dtype=torch.float64), indexing="ij")
    c = torch.zeros(270, 300, 3, 9, dtype=torch.float64)
    c[..., 0] = 1.2 + 0.4 * torch.sin(6 * x)[..., None]
    c[..., 1] = 0.3 * torch.cos(5 * y)[..., None]
    c[..., 2] = 0.2 * (x * y)[..., None] * torch.tensor([1.0, 0.5, -0.5], dtype=torch.float64)
    save_relight(tmp_path / "image", c)
    save_relight(tmp_path / "deepzoom", c, layout="deepzoom")  # two levels: 150 x 135 and 300 x 270
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    handler.log_message = lambda *a, **k: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        shots = {}
        for layout in ("image", "deepzoom"):
            out = tmp_path / f"{layout}.png"
            url = f"http://127.0.0.1:{server.server_port}/page.html?layout={layout}&dir={layout}&light=0.3,0.2"
            try:
                subprocess.run([chromium, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader",
                                "--use-angle=swiftshader", "--force-device-scale-factor=1", "--hide-scrollbars",
                                "--window-size=400,400", "--virtual-time-budget=8000", f"--screenshot={out}", url],
                               capture_output=True, timeout=120, check=True)
            except subprocess.TimeoutExpired:
                pytest.skip(f"headless {chromium} did not finish a WebGL2 screenshot in 120 s on this machine")
            shots[layout] = np.asarray(Image.open(out).convert("RGB")).astype(float)
    finally:
        server.shutdown()
    assert shots["image"].mean() > 5  # it drew something
    assert np.sqrt(((shots["image"] - shots["deepzoom"]) ** 2).mean()) < 1.0
