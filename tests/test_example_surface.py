"""End-to-end check of examples/surface_from_normals.py on a small DiLiGenT-layout folder."""

import numpy as np
import pytest
import torch

from torch_hsh.io import read_exr
from torch_hsh.io.diligent import save_diligent
from torch_hsh.render.scenes import sphere_normals
from torch_hsh.surface import integrate_normals

from _scripts import load_example


def _load_example():
    return load_example("examples/surface_from_normals.py")


def test_example_writes_depth_mesh_and_pictures(tmp_path):
    pytest.importorskip("trimesh")
    pytest.importorskip("matplotlib")
    n, m = sphere_normals(24, dtype=torch.float64)
    lights = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866]], dtype=torch.float64)
    images = (n @ lights.T).clamp(min=0).permute(2, 0, 1)[..., None].expand(3, 24, 24, 3) * 0.5
    data = save_diligent(tmp_path / "sphere", images, lights, mask=m, normals_gt=n)
    out, fig = tmp_path / "out", tmp_path / "fig.png"
    depth = _load_example().main(["--data", str(data), "--out", str(out), "--figure", str(fig)])
    for name in ("depth.npy", "depth.exr", "mesh.ply", "mesh.obj", "shaded.png"):
        assert (out / name).is_file(), name
    assert fig.is_file()
    saved = np.load(out / "depth.npy")
    # the normals went through Normal_gt.mat (float64), so the depth is the library's integration of them
    ref = integrate_normals(n, m).numpy()
    np.testing.assert_allclose(saved[m.numpy()], ref[m.numpy()], atol=1e-5)
    np.testing.assert_allclose(read_exr(out / "depth.exr")["Z"][m.numpy()], ref[m.numpy()], atol=1e-4)
    assert np.allclose(depth.numpy()[m.numpy()], saved[m.numpy()])
    with pytest.raises(SystemExit):  # never overwrites without --overwrite
        _load_example().main(["--data", str(data), "--figure", str(fig)])
