"""Tests of the comparison bases: Westin SH, Gautron HSH products, Koenderink–van Doorn Zernike, H-basis.

Every orthonormality check uses a product quadrature that is exact for the
functions involved: Gauss–Legendre in cos(theta) (on [0, 1] for the hemisphere,
[-1, 1] for the sphere) and a uniform rule in phi.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_hsh.bases import available_bases, get_basis
from torch_hsh.bases.gautron import gautron_isotropic_indices
from torch_hsh.bases.hbasis import h_basis
from torch_hsh.bases.westin import real_sh
from torch_hsh.bases.zernike import zernike_indices, zernike_mirror_coefficients, zernike_radial

DT = torch.float64
COMPARISON = ["westin_sh", "westin_sh_isotropic", "gautron_hsh", "gautron_hsh_isotropic",
              "koenderink_zernike", "koenderink_helmholtz", "koenderink_zernike_product", "hbasis",
              "hbasis_isotropic"]
NON_RECIPROCAL = ("gautron_hsh", "gautron_hsh_isotropic", "koenderink_zernike_product")


def dir_grid(n_z: int, n_phi: int, sphere: bool = False):
    """Directions and weights of a product rule over the hemisphere (or sphere): (N, 3), (N,)."""
    x, w = np.polynomial.legendre.leggauss(n_z)
    if sphere:
        z, wz = x, w
    else:
        z, wz = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    Z, PH = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z**2)
    d = np.stack([s * np.cos(PH), s * np.sin(PH), Z], -1).reshape(-1, 3)
    wt = (wz[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]).reshape(-1)
    return torch.tensor(d, dtype=DT), torch.tensor(wt, dtype=DT)


def gram_4d(basis, order, n_z=8, n_phi=12):
    sphere = basis.domain == "sphere"
    d, w = dir_grid(n_z, n_phi, sphere)
    wi, wo = d[:, None, :], d[None, :, :]
    B = basis.evaluate(wi, wo, order).reshape(-1, basis.num_functions(order))
    W = (w[:, None] * w[None, :]).reshape(-1)
    return B.T @ (B * W[:, None])


def gram_iso(basis, order, n_z=10, n_dphi=16):
    """Isotropic functions: fix phi_i = 0, integrate over dphi (the phi_i integral gives 2 pi)."""
    sphere = basis.domain == "sphere"
    x, wz = np.polynomial.legendre.leggauss(n_z)
    z, wz = (x, wz) if sphere else (0.5 * (x + 1), 0.5 * wz)
    dphi = (np.arange(n_dphi) + 0.5) * 2 * np.pi / n_dphi
    ZI, ZO, DP = np.meshgrid(z, z, dphi, indexing="ij")
    si, so = np.sqrt(1 - ZI**2), np.sqrt(1 - ZO**2)
    wi = torch.tensor(np.stack([si, 0 * si, ZI], -1).reshape(-1, 3), dtype=DT)
    wo = torch.tensor(np.stack([so * np.cos(DP), so * np.sin(DP), ZO], -1).reshape(-1, 3), dtype=DT)
    W = torch.tensor((wz[:, None, None] * wz[None, :, None] * np.full(n_dphi, 2 * np.pi / n_dphi)).reshape(-1) * 2 * np.pi)
    B = basis.evaluate(wi, wo, order)
    return B.T @ (B * W[:, None])


def random_dirs(n, gen, upper=True, dtype=DT):
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=dtype), dim=-1)
    if upper:
        d = torch.cat([d[:, :2], d[:, 2:].abs()], -1)
    return d


def rot_z(d, a):
    c, s = math.cos(a), math.sin(a)
    return torch.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)


# --------------------------------------------------------------------------- registry and counts
def test_all_comparison_bases_registered():
    names = set(available_bases())
    assert set(COMPARISON) <= names
    assert {"helmholtz_isotropic", "helmholtz_anisotropic"} <= names


def test_counts():
    z = get_basis("koenderink_zernike")
    assert [z.num_functions(n) for n in range(5)] == [1, 2, 5, 8, 14]
    assert get_basis("helmholtz_isotropic").num_functions(4) == 35
    for P in range(5):
        K = (P + 1) ** 2
        assert get_basis("westin_sh").num_functions(P) == K * (K + 1) // 2
        assert get_basis("gautron_hsh").num_functions(P) == K * K
        assert get_basis("westin_sh_isotropic").num_functions(P) == get_basis("helmholtz_isotropic").num_functions(P)
        expect = sum((P + 1 - q) ** 2 for q in range(P + 1)) + sum((P + 1 - q) ** 2 for q in range(1, P + 1))
        assert get_basis("gautron_hsh_isotropic").num_functions(P) == expect
    assert [get_basis("hbasis").num_functions(p) for p in range(3)] == [1, 10, 21]
    assert [get_basis("hbasis_isotropic").num_functions(p) for p in range(3)] == [1, 4, 5]
    # Zernike index constraints
    idx = zernike_indices(6)
    n, m, l = idx.unbind(-1)
    assert bool(((n >= m) & (m >= l) & (l >= 0) & ((n - l) % 2 == 0) & ((m - l) % 2 == 0)).all())
    assert len(gautron_isotropic_indices(3)) == get_basis("gautron_hsh_isotropic").num_functions(3)


@pytest.mark.parametrize("name", COMPARISON)
def test_shapes_labels_and_nesting(name):
    b = get_basis(name)
    gen = torch.Generator().manual_seed(1)
    wi, wo = random_dirs(7, gen), random_dirs(7, gen)
    P = min(b.max_order, 3)
    full = b.evaluate(wi, wo, P)
    assert full.shape == (7, b.num_functions(P))
    labels = b.function_orders(P)
    assert labels.shape == (b.num_functions(P),) and labels.dtype == torch.long
    for p in range(P):
        k = b.num_functions(p)
        assert int((labels <= p).sum()) == k
        assert torch.equal(labels[:k], b.function_orders(p))
        torch.testing.assert_close(full[:, :k], b.evaluate(wi, wo, p), rtol=1e-12, atol=1e-12)
    # batch shapes broadcast, float32 works
    out = b.evaluate(wi[:, None].float(), wo[None, :3].float(), P)
    assert out.shape == (7, 3, b.num_functions(P)) and out.dtype == torch.float32
    torch.testing.assert_close(out[:, 0].double(), b.evaluate(wi, wo[:1], P), rtol=1e-4, atol=1e-4)


# --------------------------------------------------------------------------- orthonormality
@pytest.mark.parametrize(
    "name,order",
    [("westin_sh", 2), ("gautron_hsh", 2), ("hbasis", 2), ("helmholtz_anisotropic", 2)],
)
def test_orthonormal_product_bases(name, order):
    b = get_basis(name)
    G = gram_4d(b, order)
    torch.testing.assert_close(G, torch.eye(G.shape[0], dtype=DT), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "name,order",
    [("westin_sh_isotropic", 4), ("gautron_hsh_isotropic", 4), ("koenderink_zernike", 4),
     ("koenderink_zernike", 8), ("koenderink_helmholtz", 5), ("koenderink_zernike_product", 4),
     ("koenderink_zernike_product", 7), ("hbasis_isotropic", 2), ("helmholtz_isotropic", 4)],
)
def test_orthonormal_isotropic_bases(name, order):
    b = get_basis(name)
    G = gram_iso(b, order, n_z=12, n_dphi=2 * order + 4)
    torch.testing.assert_close(G, torch.eye(G.shape[0], dtype=DT), rtol=0, atol=1e-11)


def test_westin_not_orthonormal_on_hemisphere_only():
    """Full-sphere SH products are not orthonormal over the hemisphere pair (why the domain is 'sphere')."""
    b = get_basis("westin_sh")
    d, w = dir_grid(8, 12, sphere=False)
    B = b.evaluate(d[:, None], d[None], 1).reshape(-1, b.num_functions(1))
    W = (w[:, None] * w[None, :]).reshape(-1)
    G = B.T @ (B * W[:, None])
    assert (G - torch.eye(G.shape[0], dtype=DT)).abs().max() > 0.1


# --------------------------------------------------------------------------- SH values
def test_real_sh_against_scipy():
    sp = pytest.importorskip("scipy.special")
    gen = torch.Generator().manual_seed(3)
    d = random_dirs(20, gen, upper=False)
    L = 6
    Y = real_sh(d, L).numpy()
    theta = np.arccos(np.clip(d[:, 2].numpy(), -1, 1))
    phi = np.arctan2(d[:, 1].numpy(), d[:, 0].numpy())
    for l in range(L + 1):
        for m in range(-l, l + 1):
            am = abs(m)
            if hasattr(sp, "sph_harm_y"):
                c = sp.sph_harm_y(l, am, theta, phi)
            else:  # pragma: no cover - older scipy
                c = sp.sph_harm(am, l, phi, theta)
            # complex Y_l^m includes the Condon–Shortley phase (-1)^m; ours does not
            if m == 0:
                ref = c.real
            elif m > 0:
                ref = math.sqrt(2) * (-1) ** am * c.real
            else:  # (-1)^m sqrt2 sin(|m| phi) N P (no CS phase)  ==  sqrt2 Im(c) since (-1)^m (-1)^m = 1
                ref = math.sqrt(2) * c.imag
            np.testing.assert_allclose(Y[:, l * l + l + m], ref, rtol=1e-10, atol=1e-12)


def test_real_sh_orthonormal_on_sphere_and_unmasked_below():
    d, w = dir_grid(10, 16, sphere=True)
    Y = real_sh(d, 4)
    torch.testing.assert_close(Y.T @ (Y * w[:, None]), torch.eye(25, dtype=DT), rtol=0, atol=1e-12)
    down = torch.tensor([[0.3, 0.2, -0.9]], dtype=DT)
    assert real_sh(down, 2).abs().sum() > 0
    assert real_sh(torch.zeros(1, 3, dtype=DT), 2).abs().sum() == 0


def test_real_sh_azimuth_convention_matches_hsh():
    """Same Phi_m as the HSH: the ratio Y_l^m / H_l^m depends on theta only (never on phi)."""
    import torch_hsh

    z = 0.6
    s = math.sqrt(1 - z * z)
    ratios = []
    for a in (0.3, 1.1, 2.0):
        d = torch.tensor([[s * math.cos(a), s * math.sin(a), z]], dtype=DT)
        ratios.append(real_sh(d, 3)[0] / torch_hsh.hsh(d, 3)[0])
    torch.testing.assert_close(ratios[0], ratios[1])
    torch.testing.assert_close(ratios[0], ratios[2])


# --------------------------------------------------------------------------- reciprocity and isotropy
def _basis_and_pairs(name, n, seed):
    """The basis, ``n`` random direction pairs on its domain and the order tested (at most 4)."""
    b = get_basis(name)
    gen = torch.Generator().manual_seed(seed)
    upper = b.domain == "hemisphere"
    return b, random_dirs(n, gen, upper), random_dirs(n, gen, upper), min(b.max_order, 4)


@pytest.mark.parametrize("name", [n for n in COMPARISON if n not in NON_RECIPROCAL])
def test_reciprocity_holds(name):
    b, wi, wo, P = _basis_and_pairs(name, 50, 5)
    assert b.reciprocal
    torch.testing.assert_close(b.evaluate(wi, wo, P), b.evaluate(wo, wi, P), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", NON_RECIPROCAL)
def test_reciprocity_fails_for_unsymmetrised_products(name):
    b = get_basis(name)
    assert not b.reciprocal
    gen = torch.Generator().manual_seed(6)
    wi, wo = random_dirs(50, gen), random_dirs(50, gen)
    diff = (b.evaluate(wi, wo, 2) - b.evaluate(wo, wi, 2)).abs().max()
    assert diff > 0.05


def test_gautron_swap_is_a_column_permutation():
    """B_jk(wi, wo) = B_kj(wo, wi): reciprocity maps the basis onto itself, just not column-wise."""
    b = get_basis("gautron_hsh")
    gen = torch.Generator().manual_seed(7)
    wi, wo = random_dirs(20, gen), random_dirs(20, gen)
    A = b.evaluate(wi, wo, 2)
    Bs = b.evaluate(wo, wi, 2)
    from torch_hsh.bases.gautron import _hsh_labels
    from torch_hsh.bases.westin import pair_table

    j, k, _, _ = pair_table(_hsh_labels(2), 2, False)
    pos = {(a, c): i for i, (a, c) in enumerate(zip(j, k))}
    perm = torch.tensor([pos[(c, a)] for a, c in zip(j, k)])
    torch.testing.assert_close(A, Bs[:, perm], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", [n for n in COMPARISON if get_basis(n).isotropic] + ["helmholtz_isotropic"])
def test_isotropy(name):
    b, wi, wo, P = _basis_and_pairs(name, 40, 8)
    ref = b.evaluate(wi, wo, P)
    for a in (0.4, 2.5):
        torch.testing.assert_close(b.evaluate(rot_z(wi, a), rot_z(wo, a), P), ref, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("name", ["westin_sh", "gautron_hsh", "hbasis"])
def test_product_bases_are_not_isotropic(name):
    b = get_basis(name)
    assert not b.isotropic
    gen = torch.Generator().manual_seed(9)
    wi, wo = random_dirs(20, gen), random_dirs(20, gen)
    assert (b.evaluate(rot_z(wi, 0.7), rot_z(wo, 0.7), 2) - b.evaluate(wi, wo, 2)).abs().max() > 0.01


@pytest.mark.parametrize(
    "iso,full,order",
    [("westin_sh_isotropic", "westin_sh", 2), ("gautron_hsh_isotropic", "gautron_hsh", 2),
     ("hbasis_isotropic", "hbasis", 2), ("helmholtz_isotropic", "helmholtz_anisotropic", 2),
     ("koenderink_helmholtz", "koenderink_zernike_product", 4)],
)
def test_isotropic_variant_lies_in_span_of_full_basis(iso, full, order):
    """Each isotropic function is a combination of the anisotropic functions of the same order."""
    bi, bf = get_basis(iso), get_basis(full)
    d, w = dir_grid(8, 12, sphere=bf.domain == "sphere")
    wi, wo = d[:, None], d[None]
    W = (w[:, None] * w[None, :]).reshape(-1)
    F = bf.evaluate(wi, wo, order).reshape(len(W), -1)
    I = bi.evaluate(wi, wo, order).reshape(len(W), -1)
    coef = F.T @ (I * W[:, None])  # projections (F is orthonormal)
    resid = I - F @ coef
    assert float((resid**2 * W[:, None]).sum(0).max()) < 1e-20
    # and each isotropic function has unit norm, so it is entirely captured
    torch.testing.assert_close((coef**2).sum(0), torch.ones(I.shape[1], dtype=DT), rtol=1e-10, atol=1e-10)


def test_westin_isotropic_is_sum_of_q_and_minus_q():
    """For q > 0: isotropic (p, r, q) = (B^{qq} + B^{-q,-q}) / sqrt2 of westin_sh (same p, r)."""
    from torch_hsh.bases.westin import _sh_gather, pair_table

    bi, bf = get_basis("westin_sh_isotropic"), get_basis("westin_sh")
    gen = torch.Generator().manual_seed(10)
    wi, wo = random_dirs(30, gen, False), random_dirs(30, gen, False)
    P = 3
    I = bi.evaluate(wi, wo, P)
    F = bf.evaluate(wi, wo, P)
    j, k, _, _ = pair_table(_sh_gather(P)[3], P, True)
    pos = {(a, c): i for i, (a, c) in enumerate(zip(j, k))}
    rows = [(p, r, q) for p in range(P + 1) for r in range(p + 1) for q in range(r + 1)]
    for col, (p, r, q) in enumerate(rows):
        if q == 0:
            continue
        a1, c1 = sorted((r * r + r + q, p * p + p + q))
        a2, c2 = sorted((r * r + r - q, p * p + p - q))
        torch.testing.assert_close(I[:, col], (F[:, pos[(a1, c1)]] + F[:, pos[(a2, c2)]]) / math.sqrt(2))


# --------------------------------------------------------------------------- domain handling
@pytest.mark.parametrize("name", [n for n in COMPARISON if get_basis(n).domain == "hemisphere"])
def test_zero_below_horizon_and_for_zero_vectors(name):
    b = get_basis(name)
    up = torch.tensor([[0.2, 0.3, 0.9]], dtype=DT)
    down = torch.tensor([[0.2, 0.3, -0.9]], dtype=DT)
    zero = torch.zeros(1, 3, dtype=DT)
    P = min(b.max_order, 2)
    assert b.evaluate(up, up, P).abs().sum() > 0
    for a, c in ((up, down), (down, up), (zero, up)):
        assert b.evaluate(a, c, P).abs().sum() == 0


def test_westin_domain_is_sphere():
    for n in ("westin_sh", "westin_sh_isotropic"):
        b = get_basis(n)
        assert b.domain == "sphere"
        down = torch.tensor([[0.2, 0.3, -0.9]], dtype=DT)
        assert b.evaluate(down, down, 2).abs().sum() > 0


@pytest.mark.parametrize("name", COMPARISON)
def test_gradients_finite_at_pole_and_horizon(name):
    b = get_basis(name)
    wi = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, 0.8]], dtype=DT, requires_grad=True)
    wo = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-0.6, 0.0, 0.8]], dtype=DT, requires_grad=True)
    b.evaluate(wi, wo, min(b.max_order, 3)).sum().backward()
    assert torch.isfinite(wi.grad).all() and torch.isfinite(wo.grad).all()


# --------------------------------------------------------------------------- errors
def test_hbasis_stops_at_six_functions():
    for n in ("hbasis", "hbasis_isotropic"):
        b = get_basis(n)
        assert b.max_order == 2
        with pytest.raises(ValueError, match="4 functions"):
            b.evaluate(torch.ones(1, 3), torch.ones(1, 3), 3)
        with pytest.raises(ValueError, match="6 functions"):
            b.num_functions(3)
    with pytest.raises(ValueError, match="Habel"):
        h_basis(torch.ones(3), 4)


@pytest.mark.parametrize("name", COMPARISON)
def test_bad_inputs(name):
    b = get_basis(name)
    with pytest.raises(ValueError, match="wi"):
        b.evaluate(torch.ones(2, 2), torch.ones(2, 3), 1)
    with pytest.raises(TypeError, match="wo"):
        b.evaluate(torch.ones(2, 3), torch.ones(2, 3, dtype=torch.int64), 1)
    with pytest.raises(ValueError):
        b.evaluate(torch.ones(2, 3), torch.ones(2, 3), -1)
    with pytest.raises(TypeError):
        b.evaluate(torch.ones(2, 3), torch.ones(2, 3), 1.5)
    with pytest.raises(ValueError, match="broadcast"):
        b.evaluate(torch.ones(2, 3), torch.ones(4, 3), 1)


# --------------------------------------------------------------------------- H-basis and Zernike specifics
def test_h_basis_values_and_orthonormality():
    d, w = dir_grid(6, 8)
    H = h_basis(d, 2)
    torch.testing.assert_close(H.T @ (H * w[:, None]), torch.eye(6, dtype=DT), rtol=0, atol=1e-13)
    p = torch.tensor([0.48, -0.6, 0.64], dtype=DT)
    c1, c2 = math.sqrt(3 / (2 * math.pi)), math.sqrt(15 / (2 * math.pi))
    ref = [1 / math.sqrt(2 * math.pi), -c1 * -0.6, c1 * (2 * 0.64 - 1), -c1 * 0.48, c2 * 0.48 * -0.6,
           0.5 * c2 * (0.48**2 - 0.36)]
    torch.testing.assert_close(h_basis(p, 2), torch.tensor(ref, dtype=DT))


def test_zernike_radial_known_polynomials():
    r = torch.linspace(0, 1, 11, dtype=DT)
    torch.testing.assert_close(zernike_radial(r, 2, 0), 2 * r**2 - 1)
    torch.testing.assert_close(zernike_radial(r, 4, 2), 4 * r**4 - 3 * r**2)
    torch.testing.assert_close(zernike_radial(r, 4, 0), 6 * r**4 - 6 * r**2 + 1)
    torch.testing.assert_close(zernike_radial(r, 3, 1), 3 * r**3 - 2 * r)
    assert zernike_radial(r, 3, 0).abs().sum() == 0
    torch.testing.assert_close(zernike_radial(torch.ones(1, dtype=DT), 7, 3), torch.ones(1, dtype=DT))


def test_zernike_uses_area_preserving_map():
    """K_{11}^1 at (theta, 0), (theta, 0) is (1/2pi) sqrt(4/2) * 2 rho^2 with rho = sqrt2 sin(theta/2)."""
    b = get_basis("koenderink_zernike")
    th = 0.9
    w = torch.tensor([[math.sin(th), 0.0, math.cos(th)]], dtype=DT)
    val = b.evaluate(w, w, 1)[0, 1]
    rho = math.sqrt(2) * math.sin(th / 2)
    assert abs(float(val) - math.sqrt(2) * 2 * rho**2 / (2 * math.pi)) < 1e-13


def mirror_projection(basis, order, n_z=24):
    """a_k = integral over the hemisphere of B_k(w, R w), R w = (-x, -y, z): the mirror kernel's projection."""
    x, wz = np.polynomial.legendre.leggauss(n_z)
    z, wz = 0.5 * (x + 1), 0.5 * wz
    s = np.sqrt(1 - z**2)
    w = torch.tensor(np.stack([s, 0 * s, z], -1), dtype=DT)
    Rw = torch.tensor(np.stack([-s, 0 * s, z], -1), dtype=DT)
    B = basis.evaluate(w, Rw, order)  # isotropic: the phi integral is 2 pi
    return 2 * math.pi * (B * torch.tensor(wz, dtype=DT)[:, None]).sum(0)


def test_zernike_mirror_spectrum_closed_form():
    """Guards the Zernike mirror spectrum used in examples/paper/mirror_lobes.py."""
    b = get_basis("koenderink_zernike")
    torch.testing.assert_close(mirror_projection(b, 8), zernike_mirror_coefficients(8), rtol=0, atol=1e-12)


def test_helmholtz_mirror_spectrum_erratum2():
    """Erratum 2: isotropic mirror coefficients are 1 (q = 0) and sqrt2 (-1)^q, not Eq. (37)'s (-1)^q / 2."""
    import torch_hsh

    b = get_basis("helmholtz_isotropic")
    a = mirror_projection(b, 6)
    idx = torch_hsh.isotropic_indices(6)
    p, r, q = idx.unbind(-1)
    sign = (-1.0) ** q.double()
    expect = torch.where(p == r, torch.where(q == 0, torch.ones_like(sign), math.sqrt(2) * sign), torch.zeros_like(sign))
    torch.testing.assert_close(a, expect, rtol=0, atol=1e-12)
    assert float(a[0]) > 0.9  # the printed value 1/2 would fail here


@pytest.mark.parametrize("name", sorted(set(COMPARISON) | {"helmholtz_isotropic", "helmholtz_anisotropic"}))
def test_azimuthal_degree_is_a_true_bound(name):
    """Every function up to P is a trigonometric polynomial of degree <= azimuthal_degree(P) in phi_i and phi_o."""
    b = get_basis(name)
    P = min(3, b.max_order)
    Dg = b.azimuthal_degree(P)
    assert Dg == P
    n = 4 * P + 8
    phi = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    for zi, zo in ((0.3, 0.8), (0.9, 0.15)):
        si, so = math.sqrt(1 - zi * zi), math.sqrt(1 - zo * zo)
        wo = torch.stack([so * torch.cos(phi), so * torch.sin(phi), torch.full_like(phi, zo)], -1)
        for a in (0.0, 1.1):  # one direction fixed, the azimuth of the other varies (both argument orders)
            wi = torch.tensor([si * math.cos(a), si * math.sin(a), zi], dtype=torch.float64).expand(n, 3)
            for B in (b.evaluate(wi, wo, P), b.evaluate(wo, wi, P)):
                spec = torch.fft.rfft(B, dim=0).abs()
                assert float(spec[Dg + 1:].max()) < 1e-10 * max(1.0, float(spec.max()))


def test_koenderink_helmholtz_is_the_symmetrised_product_basis():
    """koenderink_helmholtz = koenderink_zernike (alias); each function is (Z_nm + Z_mn)/sqrt(2 + 2 delta)."""
    from torch_hsh.bases.zernike import zernike_product_indices

    h, z, prod = get_basis("koenderink_helmholtz"), get_basis("koenderink_zernike"), get_basis("koenderink_zernike_product")
    assert h.reciprocal and h.isotropic and not prod.reciprocal
    gen = torch.Generator().manual_seed(12)
    wi, wo = random_dirs(30, gen), random_dirs(30, gen)
    P = 4
    H = h.evaluate(wi, wo, P)
    torch.testing.assert_close(H, z.evaluate(wi, wo, P), rtol=0, atol=0)
    Zp = prod.evaluate(wi, wo, P)
    pos = {tuple(r): i for i, r in enumerate(zernike_product_indices(P).tolist())}
    for col, (n, m, l) in enumerate(zernike_indices(P).tolist()):
        sym = (Zp[:, pos[(n, m, l, 0)]] + Zp[:, pos[(m, n, l, 0)]]) / math.sqrt(2 + 2 * (n == m))
        torch.testing.assert_close(H[:, col], sym, rtol=1e-11, atol=1e-12)
