"""CUDA path of the photometric-stereo solver: the same results as on the CPU (float64). Skipped without a GPU."""
import pytest
import torch

from torch_hsh import ps
from torch_hsh.brdf import BlinnPhong
from torch_hsh.render import render

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def _scene(p=300, l=32):
    dt = torch.float64
    g = torch.Generator().manual_seed(0)
    n = torch.randn(p, 3, generator=g, dtype=dt) * torch.tensor([0.4, 0.4, 0.2], dtype=dt)
    n[:, 2] += 1.0
    n = torch.nn.functional.normalize(n, dim=-1)
    d = torch.randn(l, 3, generator=g, dtype=dt) * torch.tensor([0.45, 0.45, 0.1], dtype=dt)
    d[:, 2] += 1.0
    lights = torch.nn.functional.normalize(d, dim=-1)
    alb = 0.2 + 0.6 * torch.rand(p, 3, generator=g, dtype=dt)
    img = render(n, lights, BlinnPhong(alb, torch.full((p, 1), 0.3, dtype=dt), torch.full((p, 1), 20.0, dtype=dt)),
                 read_std=1e-3, seed=0)
    return img, lights, n


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
