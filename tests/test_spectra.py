"""Closed-form Lambertian and mirror spectra (erratum 2) against numerical projection."""
import math

import pytest
import torch

import torch_hsh
from torch_hsh import fitting as F
from torch_hsh import quadrature as Q
from torch_hsh.bases import Basis, get_basis
from torch_hsh.spectra import lambertian_spectrum, mirror_spectrum, mirror_spectrum_printed

D = torch.float64


def test_lambertian_spectrum_closed_form_and_projection():
    for basis, P in (("helmholtz_isotropic", 3), ("helmholtz_anisotropic", 2)):
        s = lambertian_spectrum(0.4, P, basis)
        assert s.shape == (get_basis(basis).num_functions(P),)
        assert float(s[0]) == pytest.approx(0.8, abs=1e-15) and float(s[1:].abs().max()) == 0.0
        num = F.project(lambda wi, wo: torch.full(wi.shape[:1], 0.4 / math.pi, dtype=D), P, basis)
        assert torch.allclose(num, s, atol=1e-13)
    rgb = lambertian_spectrum(torch.tensor([0.1, 0.5, 0.9]), 1)
    assert rgb.shape == (3, 4) and rgb.dtype == torch.float32
    assert torch.allclose(rgb[:, 0], torch.tensor([0.2, 1.0, 1.8]))
    with pytest.raises(TypeError, match="albedo"):
        lambertian_spectrum("0.5", 1)


def test_lambertian_spectrum_generic_basis_path():
    class Wrapped(Basis):
        name = "wrapped_iso"
        isotropic = True
        max_order = 40

        def evaluate(self, wi, wo, order):
            return torch_hsh.helmholtz_isotropic(wi, wo, order)

        def num_functions(self, order):
            return torch_hsh.num_isotropic(order)

        def function_orders(self, order):
            return torch_hsh.isotropic_indices(order)[:, 0]

    s = lambertian_spectrum(0.3, 2, Wrapped())
    assert torch.allclose(s, lambertian_spectrum(0.3, 2), atol=1e-13)


def test_mirror_values():
    iso = mirror_spectrum(3)
    idx = torch_hsh.isotropic_indices(3)
    for (p, r, q), v in zip(idx.tolist(), iso.tolist()):
        exp = 0.0 if p != r else (1.0 if q == 0 else math.sqrt(2) * (-1) ** q)
        assert v == pytest.approx(exp, abs=1e-15)
    an = mirror_spectrum(2, basis="helmholtz_anisotropic")
    for (p, q, r, s), v in zip(torch_hsh.anisotropic_indices(2).tolist(), an.tolist()):
        assert v == pytest.approx((-1) ** q if (p == r and q == s) else 0.0, abs=1e-15)
    # the printed Eq. (37) values are exactly half
    assert torch.allclose(mirror_spectrum_printed(3), iso / 2)
    assert torch.allclose(mirror_spectrum_printed(2, basis="helmholtz_anisotropic"), an / 2)
    assert mirror_spectrum(2, dtype=torch.float32).dtype == torch.float32
    assert torch.equal(mirror_spectrum(2, get_basis("helmholtz_anisotropic")), an)


@pytest.mark.parametrize("bad", [True, False, "isotropic", "gautron_hsh", None])
def test_mirror_spectrum_basis_is_a_helmholtz_name(bad):
    with pytest.raises(ValueError, match="`basis` must be 'helmholtz_isotropic' or 'helmholtz_anisotropic'"):
        mirror_spectrum(2, bad)
    with pytest.raises(ValueError, match="`basis`"):
        mirror_spectrum_printed(2, basis=bad)


@pytest.mark.parametrize("basis,P", [("helmholtz_isotropic", 4), ("helmholtz_anisotropic", 2)])
def test_mirror_equals_delta_integral(basis, P):
    # a_k = int_{Omega} B_k(w, R w) dw for f = delta(theta_i - theta_o) delta(phi_i - phi_o + pi) / sin(theta_i)
    d, w = Q.direction_quadrature(P + 2, 4 * P + 2)
    Rd = d * torch.tensor([-1.0, -1.0, 1.0], dtype=D)
    B = getattr(torch_hsh, basis)(d, Rd, P)
    num = (B * w[:, None]).sum(0)
    assert float((num - mirror_spectrum(P, basis)).abs().max()) < 1e-12
    assert float((num - mirror_spectrum_printed(P, basis)).abs().max()) > 0.4


def test_mirror_limit_of_narrowing_lobe():
    """Normalised reciprocal lobes tending to Eq. (28) converge to the corrected spectrum, not the printed one.

    f_k(wi, wo) = [exp(k (R wi . wo - 1)) + exp(k (-wi . wo - 1))] / Z(k), Z = 2 pi (1 - e^{-2k}) / k,
    with R wi the mirror direction. The second (image) lobe reflects the part of the first that falls
    below the horizon, so int f_k(wi, wo) dwo = 1 for every wi; f_k is reciprocal and isotropic.
    """

    def lobe(k):
        Z = 2 * math.pi * (-math.expm1(-2 * k)) / k

        def f(wi, wo):
            d = -wi[:, 0] * wo[:, 0] - wi[:, 1] * wo[:, 1] + wi[:, 2] * wo[:, 2]
            e = -(wi * wo).sum(-1)
            return (torch.exp(k * (d - 1)) + torch.exp(k * (e - 1))) / Z

        return f

    ref, printed = mirror_spectrum(2), mirror_spectrum_printed(2)
    errs = []
    for k, nt, npf in ((16, 16, 24), (64, 24, 40), (256, 40, 72)):
        a = F.project(lobe(k), 2, n_theta=nt, n_phi=npf)
        errs.append(float((a - ref).abs().max()))
        assert abs(float(a[0]) - 1.0) < 1e-4  # a_00^0 = 1 for every normalised lobe (up to quadrature error)
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 0.08 and errs[1] / errs[2] > 2.5  # ~ k^{-0.8}
    assert float((a - printed).abs().max()) > 0.6  # far from the printed (-1)^q / 2 values
