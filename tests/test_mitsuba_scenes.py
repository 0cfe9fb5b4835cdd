"""The Mitsuba 3 scene generator (benchmarks/mitsuba_scenes.py) at a tiny size: layout, frame, normals, cache.

Renders a 24 x 24 dome of matte rough plastic under 12 lights (8 spp) and a 24 x 24 folded height
field under 4 lights (4 spp), a few seconds on one thread. Skipped only when mitsuba (the ``bench``
extra) is not importable.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install -e '.[bench]'); "
                                      "the Mitsuba scene generator is not tested")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import mitsuba_scenes as ms  # noqa: E402

from torch_hsh import ps  # noqa: E402
from torch_hsh.io import load_diligent  # noqa: E402

DOME = dict(size=24, lights=12, spp=8, seed=0)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("mitsuba")


@pytest.fixture(scope="module")
def dome(root):
    folder, rendered = ms.ensure_scene("dome_plastic", **DOME, root=root, threads=1)
    assert rendered
    return folder


@pytest.fixture(scope="module")
def data(dome):
    return load_diligent(dome, dtype=torch.float64)


def test_dome_loads_in_the_diligent_layout(dome, data):
    d = data
    assert d.images.shape == (12, 24, 24, 3) and d.lights.shape == (12, 3)
    assert d.normals_gt is not None and bool((d.lights[:, 2] > 0).all())
    m = d.mask
    assert 150 < int(m.sum()) < 24 * 24  # the disc of radius 0.8 in a view of half-width 1.1
    assert float(d.images[:, :2, :2].abs().max()) == 0.0  # black background (the corners)
    assert float(d.images[:, m].mean()) > 0.0
    rec = json.loads((dome / "params.json").read_text())
    assert {k: rec[k] for k in ("scene", "size", "lights", "spp", "seed")} == {"scene": "dome_plastic", **DOME}
    assert rec["max_depth"] >= 4 and rec["variant"] == "scalar_rgb"


def test_frame_of_the_aov_normals(data):
    """Mitsuba's orthographic look_at(origin=[0, 0, 5], up=[0, 1, 0]) is the DiLiGenT frame: on the dome the
    right-most object pixel has n_x > 0 and the top one (smallest row index) n_y > 0."""
    d = data
    n, m = d.normals_gt, d.mask
    rows, cols = torch.nonzero(m, as_tuple=True)
    mid_r, mid_c = int(rows.float().mean().round()), int(cols.float().mean().round())
    right = int(cols[rows == mid_r].max())
    left = int(cols[rows == mid_r].min())
    top = int(rows[cols == mid_c].min())
    bottom = int(rows[cols == mid_c].max())
    assert n[mid_r, right, 0] > 0.5 and n[mid_r, left, 0] < -0.5
    assert n[top, mid_c, 1] > 0.5 and n[bottom, mid_c, 1] < -0.5
    assert n[mid_r, mid_c, 2] > 0.95


def test_normals_unit_and_lights_toward_the_light(data):
    """GT normals are unit inside the mask (zero outside); the images follow max(n.l, 0) with l as written
    (a directional emitter travels along -l): the correlation drops when l is mirrored."""
    d = data
    m = d.mask
    norms = d.normals_gt[m].norm(dim=-1)
    assert float((norms - 1).abs().max()) < 1e-6
    assert float(d.normals_gt[~m].abs().max()) == 0.0
    n, L = d.normals_gt[m], d.lights
    img = d.images[:, m].mean(-1).T  # (P, L)

    def corr(lights):
        return float(np.corrcoef((n @ lights.T).clamp(min=0).ravel(), img.ravel())[0, 1])

    c = corr(L)
    assert c > 0.95, c
    assert corr(L * torch.tensor([-1.0, 1.0, 1.0])) < c - 0.1
    assert corr(L * torch.tensor([1.0, -1.0, 1.0])) < c - 0.1


def test_per_pixel_solve_on_the_matte_dome(data):
    """A Lambertian-like (matte rough plastic) scene: the per-pixel solver's error is small."""
    torch.set_num_threads(1)
    d = data.to(dtype=torch.float32)
    ls = ps.lambertian_ls(d.images, d.lights, None, d.mask)
    e_ls = float(ps.angular_error(ls.normals.double(), d.normals_gt.double())[d.mask].mean())
    r = ps.solve_hsh(d.images, d.lights, None, d.mask, seed=0)
    e = float(ps.angular_error(r.normals.double(), d.normals_gt.double())[d.mask].mean())
    assert e_ls < 15.0, e_ls
    assert e < 10.0, (e, e_ls)


def test_cache_reuse_and_no_overwrite(dome, root, tmp_path):
    again, rendered = ms.ensure_scene("dome_plastic", **DOME, root=root, threads=1)
    assert again == dome and not rendered  # same parameters: reused
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="overwrite"):
        ms.write_scene(user, "dome_plastic", size=8, lights=3, spp=1)
    with pytest.raises(FileExistsError, match="other parameters"):
        ms.write_scene(dome, "dome_plastic", size=8, lights=3, spp=1)
    folder, rendered = ms.write_scene(user, "dome_plastic", size=8, lights=3, spp=1, overwrite=True, threads=1)
    assert rendered and (user / "notes.txt").read_text() == "keep"
    assert load_diligent(folder).images.shape == (3, 8, 8, 3)


def test_heightfield_scene_and_cli(root, capsys):
    """A folded height field (a PLY mesh with analytic vertex normals, textured rough plastic) through the CLI,
    then the same command again reuses the folder."""
    args = ["folds_plastic", "--size", "24", "--lights", "4", "--spp", "4", "--out", str(root), "--threads", "1",
            "--quiet"]
    assert ms.main(args) == 0
    assert "folds_plastic: rendered" in capsys.readouterr().out
    assert ms.main(args) == 0
    assert "folds_plastic: cached" in capsys.readouterr().out
    d = load_diligent(root / ms.folder_name("folds_plastic", 24, 4, 4, 0))
    m = d.mask
    assert int(m.sum()) > 300  # the square [-1, 1]^2 fills most of the view
    n = d.normals_gt[m]
    assert float((n.norm(dim=-1) - 1).abs().max()) < 1e-5 and bool((n[:, 2] > 0.5).all())
    assert float(n[:, :2].norm(dim=-1).max()) > 0.5  # folds: steep faces
    assert float(d.images[:, m].max()) > 0
