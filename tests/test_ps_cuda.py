"""CUDA path of the photometric-stereo solver: the same results as on the CPU (float64). Skipped without a GPU."""
import pytest
import torch

from conftest import blinn_phong_ps_scene
from torch_hsh import ps

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def _scene(p=300, l=32):
    return blinn_phong_ps_scene(p, l)


@pytest.mark.parametrize("materials", [2, None])
def test_cuda_matches_cpu_in_float64(materials):
    img, l, n = _scene()
    kw = dict(materials=materials, work_dtype=torch.float64, calibration_pixels=256)
    cpu = ps.solve_hsh(img, l, **kw)
    gpu = ps.solve_hsh(img.cuda(), l.cuda(), **kw)
    assert gpu.normals.device.type == "cuda"
    diff = ps.angular_error(gpu.normals.cpu(), cpu.normals)
    assert float(diff.mean()) < 1e-3 and float(diff.max()) < 0.1, (float(diff.mean()), float(diff.max()))
    assert torch.allclose(gpu.coefficients.cpu(), cpu.coefficients, rtol=1e-5, atol=1e-8 * float(cpu.coefficients.abs().max()))
