"""Tests for torch_hsh.surface.export (depth files, meshes, shaded pictures)."""
import sys

import numpy as np
import pytest
import torch

from torch_hsh.io import read_exr
from torch_hsh.render.scenes import sphere_normals
from torch_hsh.surface import depth_to_mesh, integrate_normals, write_depth, write_mesh, shade_depth


def _sphere(size=24):
    n, m = sphere_normals(size, dtype=torch.float64)
    return integrate_normals(n, m), n, m


@pytest.mark.parametrize("suffix", [".npy", ".exr"])
def test_write_depth_round_trip(tmp_path, suffix):
    z, _, m = _sphere()
    p = write_depth(tmp_path / f"depth{suffix}", z, m)
    if suffix == ".npy":
        back = np.load(p)
        assert back.dtype == np.float64
        np.testing.assert_array_equal(back[m.numpy()], z[m].numpy())
    else:
        ch = read_exr(p)
        back = ch["Z"]
        np.testing.assert_allclose(back[m.numpy()], z[m].numpy(), rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(ch["mask"], m.numpy().astype(np.float32))
    assert np.isnan(back[~m.numpy()]).all()
    with pytest.raises(FileExistsError):
        write_depth(p, z, m)
    write_depth(p, z, m, overwrite=True)
    with pytest.raises(ValueError, match="npy"):
        write_depth(tmp_path / "depth.png", z, m)


def test_mesh_topology_and_orientation():
    pytest.importorskip("trimesh")
    z = torch.zeros(3, 4)
    m = torch.ones(3, 4, dtype=torch.bool)
    mesh = depth_to_mesh(z, m)
    assert len(mesh.vertices) == 12 and len(mesh.faces) == 2 * 2 * 3
    assert np.allclose(mesh.face_normals, [0, 0, 1])  # counter-clockwise seen from the camera
    assert np.isclose(mesh.area, 2 * 3)  # (W-1) (H-1) unit squares
    # vertex k is the k-th mask pixel in raster order at (col, -row, z)
    np.testing.assert_array_equal(mesh.vertices[5], [1.0, -1.0, 0.0])
    # a missing corner keeps one triangle of its block
    m[0, 0] = False
    mesh = depth_to_mesh(z, m)
    assert len(mesh.vertices) == 11 and len(mesh.faces) == 11
    assert np.allclose(mesh.face_normals, [0, 0, 1]) and np.isclose(mesh.area, 5.5)
    for r, c in [(0, 1), (1, 0), (1, 1)]:  # each other corner of a 2x2 block
        mm = torch.zeros(3, 4, dtype=torch.bool)
        mm[:2, :2] = True
        mm[r, c] = False
        one = depth_to_mesh(z, mm)
        assert len(one.faces) == 1 and np.allclose(one.face_normals, [0, 0, 1])


def test_mesh_geometry_normals_colours():
    pytest.importorskip("trimesh")
    z, n, m = _sphere()
    albedo = torch.rand(24, 24, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    mesh = depth_to_mesh(z, m, n, albedo, white=1.0)
    rows, cols = np.nonzero(m.numpy())
    np.testing.assert_allclose(mesh.vertices[:, 2], z.numpy()[rows, cols])
    np.testing.assert_allclose(mesh.vertex_normals, n.numpy()[rows, cols], atol=1e-7)
    assert (mesh.face_normals[:, 2] > 0).all()  # a dome seen from the camera
    a = albedo.numpy()[rows, cols]
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(mesh.visual.vertex_colors[:, :3], np.round(255 * srgb), atol=0.5)
    # default normals: those of the depth, close to the sphere's inside the rim
    auto = depth_to_mesh(z, m)
    cos = (auto.vertex_normals * n.numpy()[rows, cols]).sum(-1)
    assert np.median(cos) > 0.999


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_write_mesh_round_trip(tmp_path, suffix):
    trimesh = pytest.importorskip("trimesh")
    z, n, m = _sphere()
    albedo = torch.full((24, 24), 0.25, dtype=torch.float64)
    p = write_mesh(tmp_path / f"s{suffix}", z, m, n, albedo)
    ref = depth_to_mesh(z, m, n, albedo)
    back = trimesh.load(p, process=False)
    assert back.faces.shape == ref.faces.shape
    np.testing.assert_allclose(back.vertices, ref.vertices, atol=1e-6)
    np.testing.assert_allclose(back.vertex_normals, ref.vertex_normals, atol=1e-6)
    np.testing.assert_array_equal(back.visual.vertex_colors, ref.visual.vertex_colors)
    with pytest.raises(FileExistsError):
        write_mesh(p, z, m)
    with pytest.raises(ValueError, match="ply"):
        write_mesh(tmp_path / "s.stl", z, m)


def test_missing_trimesh_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "trimesh", None)
    z, _, m = _sphere()
    with pytest.raises(ImportError, match=r"pip install torch-hsh\[mesh\]"):
        depth_to_mesh(z, m)


def test_shade_depth_values():
    z = torch.zeros(6, 8, dtype=torch.float64)
    m = torch.ones(6, 8, dtype=torch.bool)
    m[0] = False
    img = shade_depth(z, m, light=(0.6, 0.0, 0.8), ambient=0.2, linear=True, background=0.5)
    assert torch.allclose(img[m], torch.tensor(0.2 + 0.8 * 0.8, dtype=torch.float64))
    assert bool((img[~m] == 0.5).all())
    # a ramp rising to the right faces left: lit from the left, darker from the right
    ramp = torch.arange(8.0, dtype=torch.float64)[None].expand(6, 8) * 0.5
    left = shade_depth(ramp, light=(-0.6, 0.0, 0.8), ambient=0.0, linear=True)
    right = shade_depth(ramp, light=(0.6, 0.0, 0.8), ambient=0.0, linear=True)
    assert bool((left > right).all())
    colour = shade_depth(z, m, albedo=torch.tensor([1.0, 0.5, 0.0]).expand(6, 8, 3).double(), linear=True, light=(0, 0, 1))
    assert colour.shape == (6, 8, 3) and torch.allclose(colour[3, 3], torch.tensor([1.0, 0.5, 0.0]).double())
    enc = shade_depth(z, m, light=(0.6, 0.0, 0.8), ambient=0.2)
    assert torch.allclose(enc[m], torch.tensor(1.055 * 0.84 ** (1 / 2.4) - 0.055, dtype=torch.float64))
    # cast shadows: a wall darkens its foot
    wall = torch.zeros(10, 30, dtype=torch.float64)
    wall[:, 20:] = 10.0
    sh = shade_depth(wall, light=(0.6, 0.0, 0.8), ambient=0.1, shadows=True, linear=True)
    assert torch.allclose(sh[5, 15], torch.tensor(0.1, dtype=torch.float64)) and float(sh[5, 2]) > 0.8
    with pytest.raises(ValueError, match="light"):
        shade_depth(z, m, light=(0.0, 0.0, 0.0))
