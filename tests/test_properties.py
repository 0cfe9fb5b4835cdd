"""Properties that must hold, tested with generated inputs (hypothesis).

* Photometric stereo is covariant: rotating the lights and the scene about the view axis rotates the
  recovered normals (the solvers' tangent frame is azimuthal, :func:`torch_hsh.ps._geometry.tangent_frame`);
  scaling the images or the light intensities by 1e-6 .. 1e6 leaves the normals unchanged.
* Reciprocity and isotropy of the bases and BRDF models that declare them; non-negativity where it is
  promised (the analytic models, ``HelmholtzBRDF(nonnegative=True)``, :func:`torch_hsh.rti.nonnegative_rti`).
* A BRDF in the span of a basis: :func:`torch_hsh.fitting.fit` and :func:`torch_hsh.fitting.project`
  recover its coefficients exactly.
* Degenerate photometric-stereo inputs (NaN / Inf observations, zero-intensity or duplicated lights, a
  one-pixel mask, images saturated or dark everywhere, float16 / bfloat16): a correct result, a flagged
  one (confidence 0, ``info['fallback_pixels']``, a warning) or an error naming the argument.

The scenes are tiny (36 pixels, 20 lights) and every property draws few examples. Tolerances: the default
(shared) model iterates in float32 (``work_dtype``), so its normals agree to 5e-4 rad; the independent model
runs in float64 and agrees to 1e-6 rad.
"""
from __future__ import annotations

import math
import warnings
from functools import lru_cache

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import random_ps_scene
from torch_hsh import HelmholtzBRDF, ps
from torch_hsh.bases import available_bases, get_basis
from torch_hsh.brdf import BlinnPhong, get_model
from torch_hsh.fitting import fit, project
from torch_hsh.ps._geometry import tangent_frame
from torch_hsh.render import render
from torch_hsh.rti import evaluate_rti, nonnegative_rti
from torch_hsh.rti.fitting import OPENLIME_THETA_CLAMP, _cap_grid

F64 = torch.float64
P, L = 36, 20  # pixels, lights of the scene
#: solver options and the tolerance (radians) of the normals' agreement
MODELS = {"shared": ({}, 5e-4), "independent": ({"materials": None}, 1e-6)}
FEW = settings(max_examples=3, deadline=None)


def _rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


def _render(normals, lights, albedo):
    model = BlinnPhong(albedo, torch.full((P, 1), 0.3, dtype=F64), torch.full((P, 1), 20.0, dtype=F64))
    return render(normals, lights, model)


@lru_cache(maxsize=None)
def _scene():
    """``(images (L, P, 3), lights (L, 3), normals (P, 3), albedo (P, 3))``: a glossy (Blinn-Phong) scene."""
    n, lights, g = random_ps_scene(P, L, 3, spread=0.4)
    albedo = 0.2 + 0.6 * torch.rand(P, 3, generator=g, dtype=F64)
    return _render(n, lights, albedo), lights, n, albedo


@lru_cache(maxsize=None)
def _reference(model: str):
    """The normals ``(P, 3)`` and per-pixel errors in degrees of the solve of :func:`_scene`."""
    images, lights, n, _ = _scene()
    normals = ps.solve_hsh(images, lights, **MODELS[model][0]).normals
    return normals, ps.angular_error(normals, n)


def _angle(a, b):
    return torch.deg2rad(ps.angular_error(a.to(F64), b.to(F64)))


def _assert_unit(normals):
    assert bool(torch.isfinite(normals).all())
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(normals.shape[:-1], dtype=normals.dtype))


# ---- the tangent frame of the solvers

@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 2 * math.pi), st.floats(-1.0, 1.0), st.floats(1e-6, 1.0), st.floats(0.0, 2 * math.pi))
def test_tangent_frame_orthonormal_and_covariant(phi, z, r, angle):
    n = torch.nn.functional.normalize(torch.tensor([[r * math.cos(phi), r * math.sin(phi), z]], dtype=F64), dim=-1)
    t1, t2 = tangent_frame(n)
    frame = torch.stack([t1, t2, n], dim=-2)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), torch.eye(3, dtype=F64)[None], atol=1e-12, rtol=0)
    assert float(torch.linalg.det(frame)) == pytest.approx(1.0, abs=1e-12)  # right-handed
    R = _rot_z(angle)
    r1, r2 = tangent_frame(n @ R.T)
    torch.testing.assert_close(r1, t1 @ R.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(r2, t2 @ R.T, atol=1e-12, rtol=0)


def test_tangent_frame_at_the_poles():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=F64)
    t1, t2 = tangent_frame(n)
    frame = torch.stack([t1, t2, n], dim=-2)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), torch.eye(3, dtype=F64).expand(2, 3, 3))
    torch.testing.assert_close(t1, torch.tensor([[0.0, 1.0, 0.0]] * 2, dtype=F64))


# ---- photometric stereo: covariance and invariance

@pytest.mark.slow
@pytest.mark.parametrize("model", list(MODELS))
@FEW
@given(angle=st.floats(0.0, 2 * math.pi))
def test_ps_rotation_about_the_view_axis_rotates_the_normals(model, angle):
    images, lights, n, albedo = _scene()
    R = _rot_z(angle)
    # the premise: an isotropic scene and its lights rotated about the view axis give the same images
    torch.testing.assert_close(_render(n @ R.T, lights @ R.T, albedo), images, atol=1e-12, rtol=1e-10)
    rotated = ps.solve_hsh(images, lights @ R.T, **MODELS[model][0]).normals
    assert float(_angle(rotated, _reference(model)[0] @ R.T).max()) <= MODELS[model][1]


@pytest.mark.slow
@pytest.mark.parametrize("model", list(MODELS))
@FEW
@given(k=st.floats(-6.0, 6.0), target=st.sampled_from(["images", "intensities", "per-light"]))
def test_ps_normals_do_not_depend_on_the_brightness_scale(model, k, target):
    images, lights, _, _ = _scene()
    opts = dict(MODELS[model][0])
    if target == "images":
        images = images * 10.0**k
    elif target == "intensities":  # the same intensity for every light: the data are divided by it
        opts["intensities"] = torch.full((L,), 10.0**k, dtype=F64)
    else:  # per light and channel, in the images and the intensities alike
        u = torch.rand(L, 3, generator=torch.Generator().manual_seed(1), dtype=F64) * 2 - 1
        opts["intensities"] = 10.0 ** (k * u)
        images = images * opts["intensities"][:, None, :]
    normals = ps.solve_hsh(images, lights, **opts).normals
    assert float(_angle(normals, _reference(model)[0]).max()) <= MODELS[model][1]


# ---- reciprocity, isotropy, non-negativity

_DIR = st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 2 * math.pi))
_PAIRS = st.lists(st.tuples(_DIR, _DIR), min_size=1, max_size=8)


def _dirs(pairs):
    """``wi, wo (M, 3)`` from ``((cos theta, phi), (cos theta, phi))`` pairs."""
    def one(zs):
        z = torch.tensor([c for c, _ in zs], dtype=F64)
        phi = torch.tensor([p for _, p in zs], dtype=F64)
        s = (1 - z * z).clamp(min=0).sqrt()
        return torch.stack([s * phi.cos(), s * phi.sin(), z], dim=-1)
    return one([a for a, _ in pairs]), one([b for _, b in pairs])


def _close(a, b, rel=1e-10):
    torch.testing.assert_close(a, b, rtol=0, atol=rel * max(1.0, float(a.abs().max())))


@settings(max_examples=15, deadline=None)
@given(_PAIRS, st.floats(0.0, 2 * math.pi))
def test_bases_reciprocal_and_isotropic_as_declared(pairs, angle):
    wi, wo = _dirs(pairs)
    R = _rot_z(angle)
    for name in available_bases():
        b = get_basis(name)
        order = min(2, b.max_order or 2)
        v = b.evaluate(wi, wo, order)
        if b.reciprocal:
            _close(b.evaluate(wo, wi, order), v)
        if b.isotropic:
            _close(b.evaluate(wi @ R.T, wo @ R.T, order), v, 1e-9)


_MODEL_PARAMS = {
    "lambertian": dict(albedo=st.floats(0.0, 1.0)),
    "ggx": dict(albedo=st.floats(0.0, 1.0), specular=st.floats(0.0, 2.0), roughness=st.floats(0.05, 1.0),
                f0=st.floats(0.0, 1.0)),
    "blinn_phong": dict(albedo=st.floats(0.0, 1.0), specular=st.floats(0.0, 2.0), shininess=st.floats(0.0, 200.0)),
    "oren_nayar": dict(albedo=st.floats(0.0, 1.0), sigma=st.floats(0.0, 1.0)),
    "ward": dict(albedo=st.floats(0.0, 1.0), specular=st.floats(0.0, 1.0), alpha_x=st.floats(0.05, 1.0),
                 alpha_y=st.floats(0.05, 1.0)),
    "torrance_sparrow": dict(albedo=st.floats(0.0, 1.0), specular=st.floats(0.0, 1.0), sigma=st.floats(0.05, 1.0),
                             eta=st.floats(1.05, 3.0)),
}


def test_every_model_is_covered():
    from torch_hsh.brdf import available_models

    assert sorted(_MODEL_PARAMS) == sorted(available_models())


@settings(max_examples=30, deadline=None)
@given(st.sampled_from(sorted(_MODEL_PARAMS)).flatmap(lambda m: st.tuples(st.just(m), st.fixed_dictionaries(
    _MODEL_PARAMS[m]))), _PAIRS, st.floats(0.0, 2 * math.pi))
def test_models_nonnegative_reciprocal_and_isotropic_as_declared(named, pairs, angle):
    name, params = named
    f = get_model(name, **params)
    wi, wo = _dirs(pairs)
    v = f(wi, wo)
    assert bool(torch.isfinite(v).all()) and float(v.min()) >= 0.0
    if f.reciprocal:
        _close(f(wo, wi), v)
    if f.isotropic:
        R = _rot_z(angle)
        _close(f(wi @ R.T, wo @ R.T), v, 1e-9)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1), _PAIRS)
def test_helmholtz_brdf_reciprocal_and_nonnegative_when_asked(seed, pairs):
    coef = torch.randn(2, 20, generator=torch.Generator().manual_seed(seed), dtype=F64)
    plain = HelmholtzBRDF(order=3, channels=2, init=coef, dtype=F64, learnable=False)
    clamped = HelmholtzBRDF(order=3, channels=2, init=coef, dtype=F64, learnable=False, nonnegative=True)
    wi, wo = _dirs(pairs)
    v = plain(wi, wo)
    _close(plain(wo, wi), v)
    torch.testing.assert_close(clamped(wi, wo), v.clamp(min=0.0), rtol=0, atol=0)


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 0.2))
def test_nonnegative_rti_meets_its_bound_and_keeps_what_meets_it(seed, margin):
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(2, 3, 9, generator=g, dtype=F64) * 0.5
    c[1, :, 0] = 20.0  # the second pixel is positive everywhere already
    out = nonnegative_rti(c, margin=margin, nz=8, nphi=32)
    grid = _cap_grid(math.degrees(OPENLIME_THETA_CLAMP), 16, 64)  # where the bound is promised
    assert float(evaluate_rti(out[..., None, :], grid).min()) >= margin - 1e-9
    torch.testing.assert_close(out[1], c[1], rtol=0, atol=0)


# ---- exact recovery of a BRDF in the span of the basis

@settings(max_examples=8, deadline=None)
@given(st.sampled_from(["helmholtz_isotropic", "helmholtz_anisotropic"]), st.integers(0, 3),
       st.integers(0, 2**31 - 1))
def test_fit_and_project_recover_the_coefficients_of_a_brdf_in_the_span(basis, order, seed):
    b = get_basis(basis)
    K = b.num_functions(order)
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(2, K, generator=g, dtype=F64)
    wi, wo = (torch.nn.functional.normalize(torch.randn(4 * K + 10, 3, generator=g, dtype=F64), dim=-1)
              for _ in range(2))
    wi[:, 2], wo[:, 2] = wi[:, 2].abs(), wo[:, 2].abs()  # on the upper hemisphere
    torch.testing.assert_close(fit(wi, wo, b.evaluate(wi, wo, order) @ a.T, order, basis), a, rtol=0, atol=1e-9)
    got = project(lambda u, v: b.evaluate(u, v, order) @ a.T, order, basis, tol=None)
    torch.testing.assert_close(got, a, rtol=0, atol=1e-9)


# ---- degenerate photometric-stereo inputs

@pytest.mark.slow
@FEW
@given(st.integers(0, L - 1), st.integers(0, P - 1), st.integers(0, 2),
       st.sampled_from([float("nan"), float("inf"), -float("inf")]))
def test_ps_nonfinite_observation_is_dropped(light, pixel, channel, value):
    images, lights, _, _ = _scene()
    bad = images.clone()
    bad[light, pixel, channel] = value
    normals = ps.solve_hsh(bad, lights, materials=None).normals
    ref = _reference("independent")[0]
    others = torch.arange(P) != pixel
    assert float(_angle(normals[others], ref[others]).max()) <= 1e-6
    # that pixel is solved as if that light had not been taken, up to its start: the trimmed Lambertian
    # start counts the invalid observation among the dark ones (measured: up to 2e-3 rad)
    keep = torch.arange(L) != light
    alone = ps.solve_hsh(images[keep][:, pixel:pixel + 1], lights[keep], materials=None).normals
    assert float(_angle(normals[pixel:pixel + 1], alone).max()) <= 1e-2
    _assert_unit(ps.solve_hsh(bad, lights).normals)  # the shared model: finite unit normals


def test_ps_pixel_without_a_finite_observation_is_flagged():
    images, lights, _, _ = _scene()
    bad = images.clone()
    bad[:, 5] = float("nan")
    res = ps.solve_hsh(bad, lights)
    _assert_unit(res.normals)
    assert res.info["fallback_pixels"] == 1.0
    assert float(res.confidence[5]) == 0.0 and bool((res.confidence[torch.arange(P) != 5] > 0).all())


@FEW
@given(st.integers(0, L - 1), st.sampled_from([0.0, -1.0, float("nan"), float("inf")]), st.booleans())
def test_ps_bad_intensity_is_an_error_naming_intensities(light, value, rgb):
    images, lights, _, _ = _scene()
    e = torch.ones((L, 3) if rgb else (L,), dtype=F64)
    e[light] = value
    with pytest.raises(ValueError, match="intensities"):
        ps.solve_hsh(images, lights, intensities=e)


@pytest.mark.parametrize("model", list(MODELS))
def test_ps_every_light_twice_is_the_same_problem(model):
    images, lights, _, _ = _scene()
    opts, tol = MODELS[model]
    both = ps.solve_hsh(torch.cat([images, images]), torch.cat([lights, lights]), **opts).normals
    assert float(_angle(both, _reference(model)[0]).max()) <= 10 * tol


@pytest.mark.slow
@pytest.mark.parametrize("model", list(MODELS))
@FEW
@given(dup=st.lists(st.integers(0, L - 1), min_size=1, max_size=6, unique=True))
def test_ps_duplicated_lights(model, dup):
    """A few lights given twice (each at most twice: a light given five times is another light design, and
    its solve may legitimately differ by more) still give a sound solve."""
    images, lights, n, _ = _scene()
    idx = torch.tensor(dup)
    res = ps.solve_hsh(torch.cat([images, images[idx]]), torch.cat([lights, lights[idx]]), **MODELS[model][0])
    _assert_unit(res.normals)  # a few lights weigh more: still a sound solve
    assert float(ps.angular_error(res.normals, n).mean()) <= float(_reference(model)[1].mean()) + 1.0


@pytest.mark.parametrize("model", list(MODELS))
@FEW
@given(pixel=st.integers(0, P - 1))
def test_ps_one_pixel_mask(model, pixel):
    images, lights, n, _ = _scene()
    stack = torch.zeros(L, 6, 6, 3, dtype=F64)  # dark background around the one pixel
    stack.reshape(L, P, 3)[:, pixel] = images[:, pixel]
    mask = torch.zeros(6, 6, dtype=torch.bool)
    mask.reshape(-1)[pixel] = True
    res = ps.solve_hsh(stack, lights, mask=mask, **MODELS[model][0])
    _assert_unit(res.normals[mask])
    assert float(res.confidence[mask]) > 0
    ref = _reference("independent")[0][pixel:pixel + 1]
    # the independent model solves every pixel alone; the shared one calibrates its basis on that pixel
    assert float(_angle(res.normals[mask], ref).max()) <= (1e-6 if model == "independent" else math.radians(10))


@pytest.mark.parametrize("level", [1.0, 0.0])
def test_ps_images_saturated_or_dark_everywhere_are_flagged(level):
    images, lights, _, _ = _scene()
    with pytest.warns(UserWarning, match="fallback_pixels"):
        res = ps.solve_hsh(torch.full_like(images, level), lights)
    _assert_unit(res.normals)
    assert res.info["fallback_pixels"] == P and bool((res.confidence == 0).all())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("arg", ["images", "lights"])
def test_ps_half_precision_is_an_error_naming_the_argument(dtype, arg):
    images, lights, _, _ = _scene()
    data = {"images": images, "lights": lights}
    data[arg] = data[arg].to(dtype)
    with pytest.raises(TypeError, match=arg):
        ps.solve_hsh(data["images"], data["lights"])


def test_ps_degenerate_light_is_an_error_naming_lights():
    images, lights, _, _ = _scene()
    for bad in (torch.zeros(3, dtype=F64), torch.full((3,), float("nan"), dtype=F64)):
        with warnings.catch_warnings(), pytest.raises(ValueError, match="lights"):
            ps.solve_hsh(images, torch.cat([lights[:-1], bad[None]]))
