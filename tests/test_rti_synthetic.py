"""The synthetic RTI capture generator (torch_hsh.rti.synthetic)."""
import warnings

import numpy as np
import pytest

from torch_hsh.ps.lambertian import robust_lambertian
from torch_hsh.rti.io import load_rti, read_lp
from torch_hsh.rti.synthetic import synthetic_normals, write_synthetic_capture


def _angles(n, gt):
    return np.degrees(np.arccos(np.clip((n * gt).sum(-1), -1.0, 1.0)))


def test_small_capture_loads_and_lambertian_recovers_normals(tmp_path):
    folder = write_synthetic_capture(tmp_path / "cap", 64, 48, 8, band_rows=16)
    names, _, lights = read_lp(folder / "lights.lp")
    assert len(names) == 8 and lights.shape == (8, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # no mask.png
        data = load_rti(folder)
    assert tuple(data.images.shape) == (8, 48, 64, 3)
    gt = np.load(folder / "normals_gt.npy")
    assert gt.shape == (48, 64, 3) and np.allclose(np.linalg.norm(gt, axis=-1), 1.0, atol=1e-5)
    assert set(np.unique(np.load(folder / "materials_gt.npy"))) == {0, 1, 2}
    n = robust_lambertian(data.images.double(), data.lights.double()).normals.numpy()
    ang = _angles(n, gt)
    assert np.median(ang) < 3.0 and ang.mean() < 6.0


def test_bands_do_not_change_the_capture(tmp_path):
    a = write_synthetic_capture(tmp_path / "a", 40, 30, 4, band_rows=7)
    b = write_synthetic_capture(tmp_path / "b", 40, 30, 4, band_rows=30)
    assert np.array_equal(np.load(a / "normals_gt.npy"), np.load(b / "normals_gt.npy"))
    assert (a / "img_0001.jpg").read_bytes() == (b / "img_0001.jpg").read_bytes()
    n, m = synthetic_normals(40, 30, slice(5, 9))
    assert n.shape == (4, 40, 3) and m.shape == (4, 40)


def test_bad_sizes_are_refused(tmp_path):
    with pytest.raises(ValueError):
        write_synthetic_capture(tmp_path / "c", 0, 10, 8)
    with pytest.raises(ValueError):
        write_synthetic_capture(tmp_path / "c", 10, 10, 2)
