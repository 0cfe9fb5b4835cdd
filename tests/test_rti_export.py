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
