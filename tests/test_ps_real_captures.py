"""Real-capture behaviour of the photometric-stereo solver (issue: crashes at full resolution, NaN pixels,
image units, confidence, frame-independent noise estimate).

Sizes above 2**24 are reached with cheap helper calls, not full solves.
"""
import math

import warnings

import pytest
import torch

from conftest import blinn_phong_ps_scene
from torch_hsh import ps
from torch_hsh.ps.observations import (
    QUANTILE_MAX_ELEMENTS,
    background_ring,
    prepare_inputs,
    robust_sigma,
    row_quantile,
    strided_sample,
)

DT = torch.float64
FAST = dict(calibration_pixels=256, calibration_rounds=4, max_iter=4)


def _scene(p=120, l=24, seed=0, dtype=DT):
    img, lights, n = blinn_phong_ps_scene(p, l, seed)
    return img.to(dtype), lights.to(dtype), n


# ---------------------------------------------------------------- sizes beyond 2**24
def test_strided_sample_stays_in_bounds_beyond_float32_integers():
    """A float32 linspace rounds the last index of 2**24 + 4 elements past the end (the old crash)."""
    N = 2**24 + 4  # N - 1 = 2**24 + 3 is not a float32: it rounds up to N
    x = torch.arange(N, dtype=torch.int64)
    s = strided_sample(x, 2_000_000)
    assert s.numel() == 2_000_000 and int(s[0]) == 0 and int(s[-1]) == N - 1
    assert bool((s[1:] > s[:-1]).all())
    old = torch.linspace(0, N - 1, 2_000_000).long()  # what the solver used to do
    assert int(old.max()) >= N  # ... which indexes out of bounds


def test_robust_sigma_of_more_than_2_24_background_values():
    g = torch.Generator().manual_seed(0)
    x = 0.01 * torch.randn(2**24 + 1000, generator=g)
    assert robust_sigma(x) == pytest.approx(0.01, rel=0.02)


def test_observation_weights_beyond_the_quantile_limit():
    """``torch.quantile`` refuses more than 2**24 elements; the dark threshold is per pixel, so rows are chunked."""
    P, L = QUANTILE_MAX_ELEMENTS // 96 + 50, 96
    g = torch.Generator().manual_seed(1)
    y = torch.rand(P, L, 1, generator=g)
    w, info = ps.observation_weights(y, y)
    assert w.shape == (P, L) and info["dark_fraction"] > 0
    sub = y[:1000, :, 0]
    assert torch.equal(row_quantile(y[..., 0], 0.75)[:1000], torch.quantile(sub, 0.75, dim=1, keepdim=True))


# ---------------------------------------------------------------- invalid observations stay local
def test_one_nan_observation_stays_local():
    img, l, n = _scene()
    clean = ps.solve_hsh(img, l, **FAST)
    bad = img.clone()
    bad[3, 17, 1] = float("nan")
    bad[5, 40, :] = -1.0  # negative: invalid too
    bad[7, 41, 0] = float("inf")
    r = ps.solve_hsh(bad, l, **FAST)
    for t in (r.normals, r.coefficients, r.albedo, r.basis_brdfs, r.mixing, r.residual, r.confidence):
        assert bool(torch.isfinite(t).all())
    assert r.info["invalid_fraction"] > 0  # (negative read noise in the shadows is invalid too)
    assert r.weights[17, 3] == 0 and r.weights[40, 5] == 0 and r.weights[41, 7] == 0
    err_clean = float(ps.angular_error(clean.normals, n).mean())
    err_bad = float(ps.angular_error(r.normals, n).mean())
    assert err_bad < err_clean + 0.2, (err_clean, err_bad)


def test_valid_argument_excludes_observations_like_invalid_values():
    img, l, _ = _scene(p=60, l=20, seed=3)
    valid = torch.ones(img.shape[:2], dtype=torch.bool)
    valid[2, 10] = False
    valid[4, :5] = False
    a = ps.solve_hsh(img, l, valid=valid, **FAST)
    nan = img.clone()
    nan[~valid] = float("nan")
    b = ps.solve_hsh(nan, l, **FAST)
    assert torch.equal(a.normals, b.normals)
    with pytest.raises(ValueError, match="valid"):
        ps.solve_hsh(img, l, valid=valid[:3], **FAST)


# ---------------------------------------------------------------- units
@pytest.mark.parametrize("scale", [1e-10, 1e20])
def test_normals_do_not_depend_on_the_image_units(scale):
    img, l, n = _scene(seed=4)
    ref = ps.solve_hsh(img.float(), l.float(), **FAST)
    r = ps.solve_hsh((img * scale).float(), l.float(), **FAST)
    assert bool(torch.isfinite(r.coefficients).all()) and bool(torch.isfinite(r.normals).all())
    diff = ps.angular_error(r.normals, ref.normals)
    assert float(diff.mean()) < 0.05 and float(diff.max()) < 1.0, (float(diff.mean()), float(diff.max()))
    # coefficients carry the units of the images
    rel = (r.coefficients / scale - ref.coefficients).abs().max() / ref.coefficients.abs().max()
    assert float(rel) < 0.05


# ---------------------------------------------------------------- every pixel gets a normal, and a confidence
def test_pixels_without_enough_observations_get_a_normal_and_zero_confidence():
    img, l, n = _scene(p=80, l=16, seed=5)
    img[:, 0] = float("nan")  # nothing valid
    img[:14, 1] = float("nan")  # two valid observations
    img[:13, 2] = 0.0  # three observations left above the dark threshold
    r = ps.solve_hsh(img, l, **FAST)
    nrm = r.normals.norm(dim=-1)
    assert bool(torch.isfinite(r.normals).all()) and torch.allclose(nrm, torch.ones_like(nrm))
    assert float(r.confidence[0]) == 0 and float(r.confidence[1]) == 0 and float(r.confidence[2]) == 0
    assert r.info["fallback_pixels"] >= 3
    c = r.confidence[3:]
    assert bool(((c >= 0) & (c <= 1)).all()) and float(c.mean()) > 0.5


def test_a_warning_when_most_pixels_fall_back():
    # three lights leave 3 valid observations per pixel: every pixel keeps its Lambertian normal, which is said
    img, l, n = _scene(p=40, l=16, seed=5)
    msg = r"40 of 40 pixels keep a Lambertian normal .* 40 have fewer than 4 valid observations of 3 lights\. "
    with pytest.warns(UserWarning, match=msg):
        r = ps.solve_hsh(img[:3], l[:3], **FAST)
    assert r.info["fallback_pixels"] == 40 and float(r.confidence.max()) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a few fallback pixels are normal (shadows) and say nothing
        img[:13, :3] = 0.0
        assert ps.solve_hsh(img, l, **FAST).info["fallback_pixels"] >= 3


def test_confidence_is_low_where_the_model_does_not_fit():
    img, l, n = _scene(p=150, l=30, seed=6)
    g = torch.Generator().manual_seed(7)
    img[:, :20] = img[:, :20] * (0.3 + 1.4 * torch.rand(30, 20, 1, generator=g, dtype=DT))  # random flicker
    r = ps.solve_hsh(img, l, **FAST)
    assert float(r.confidence[:20].mean()) < 0.5 * float(r.confidence[20:].mean())


def test_confidence_map_is_zero_outside_the_mask():
    img, l, _ = _scene(p=64, l=20, seed=8)
    img = img.reshape(20, 8, 8, 3)
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[2:7, 1:6] = True
    r = ps.solve_hsh(img, l, mask=mask, **FAST)
    assert r.confidence.shape == (8, 8) and bool((r.confidence[~mask] == 0).all())


# ---------------------------------------------------------------- the frame around the object
def _framed(frame, seed=9):
    """A 24x24 object (random normals) on a noisy dark background, centred in a ``frame`` x ``frame`` image;
    the far background (beyond 20 px of the object) is much noisier, as a lit room would be."""
    img, l, _ = _scene(p=24 * 24, l=20, seed=seed)
    g = torch.Generator().manual_seed(seed)
    full = 0.002 * torch.randn(20, frame, frame, 3, generator=g, dtype=DT).abs()
    far = torch.ones(frame, frame, dtype=torch.bool)
    o = (frame - 24) // 2
    far[max(0, o - 20): o + 44, max(0, o - 20): o + 44] = False
    full[:, far] = full[:, far] * 20.0
    full[:, o:o + 24, o:o + 24] = img.reshape(20, 24, 24, 3)
    mask = torch.zeros(frame, frame, dtype=torch.bool)
    mask[o:o + 24, o:o + 24] = True
    return full, l, mask


def test_noise_estimate_does_not_depend_on_the_frame_around_the_object():
    img, l, mask = _framed(160)
    b = prepare_inputs(img, l, mask=mask)
    a = prepare_inputs(img[:, 48:112, 48:112], l, mask=mask[48:112, 48:112])  # a 20-px margin crop
    assert a.y.shape == b.y.shape
    assert robust_sigma(a.background) == pytest.approx(robust_sigma(b.background), rel=1e-6)
    ring = background_ring(mask)
    assert not bool((ring & mask).any()) and int(ring.sum()) == (24 + 32) ** 2 - (24 + 4) ** 2


def test_object_filling_the_frame_has_no_background_and_still_solves():
    img, l, n = _scene(p=100, l=20, seed=10)
    r = ps.solve_hsh(img.reshape(20, 10, 10, 3), l, **FAST)
    assert r.info["noise_sigma"] == 0.0
    assert bool(torch.isfinite(r.normals).all())
    lam = ps.robust_lambertian(img, l)
    err = float(ps.angular_error(r.normals.reshape(-1, 3), n).mean())
    assert err < float(ps.angular_error(lam.normals, n).mean()), err


@pytest.mark.parametrize("bad", [dict(noise_sigma=-1.0), dict(noise_sigma=float("nan")), dict(dark_fraction=2.0),
                                 dict(saturation=0.0), dict(dark_fraction=-0.1)])
def test_threshold_arguments_are_validated(bad):
    img, l, _ = _scene(p=10, l=8)
    name = next(iter(bad))
    with pytest.raises(ValueError, match=name):
        ps.solve_hsh(img, l, **bad)


def test_coefficient_buffer_choice_follows_the_lower_peak():
    from torch_hsh.ps.coefficients import _write_map_in_place

    # 1024^2 x 96 RGB float32 observations, 667k masked pixels, float64 coefficients: compact buffer
    assert not _write_map_in_place(667_064, 1024 * 1024, 96, 3, 20, 4, 8)
    # 2048^2 x 16: the map is written in place
    assert _write_map_in_place(2_670_000, 2048 * 2048, 16, 3, 20, 4, 8)


@pytest.mark.parametrize("in_place", [False, True])
def test_coefficient_map_is_the_same_written_in_place_or_scattered(in_place, monkeypatch):
    from torch_hsh.ps import coefficients

    img, l, _ = _scene(p=64, l=20, seed=8)
    img = img.reshape(20, 8, 8, 3)
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[2:7, 1:6] = True
    mask[4, 3] = False
    ref = ps.solve_hsh(img, l, mask=mask, **FAST)
    monkeypatch.setattr(coefficients, "_write_map_in_place", lambda *a: in_place)
    r = ps.solve_hsh(img, l, mask=mask, **FAST)
    assert torch.equal(r.coefficients, ref.coefficients) and torch.equal(r.albedo, ref.albedo)
    assert bool((r.coefficients[~mask] == 0).all()) and bool((r.coefficients[mask] != 0).any())


def test_given_basis_skips_the_calibration_and_reproduces_the_solve():
    img, l, n = _scene(p=200, l=24, seed=3)
    r = ps.solve_hsh(img, l, **FAST)
    r2 = ps.solve_hsh(img, l, basis=r.basis_brdfs, robust_scale=r.info["robust_scale"], init=r.normals, **FAST)
    assert r2.info["basis_given"] == 1.0 and r2.info["calibration_pixels"] == 0.0
    assert r2.info["robust_scale"] == pytest.approx(r.info["robust_scale"], rel=1e-12)
    assert torch.allclose(r2.basis_brdfs, r.basis_brdfs)
    # from the first solve's normals, the per-pixel pass stays there
    assert float(ps.angular_error(r2.normals, r.normals).mean()) < 0.5
    # in other image units, with the scale estimated: same normals up to the estimate
    r3 = ps.solve_hsh(img * 1000.0, l, basis=r.basis_brdfs, init=r.normals, **FAST)
    assert r3.info["robust_scale_estimated"] == 1.0
    assert float(ps.angular_error(r3.normals, n).mean()) < float(ps.angular_error(r.normals, n).mean()) + 1.0


@pytest.mark.parametrize("kw, name", [
    (dict(basis=torch.zeros(2, 20, dtype=DT)), "basis"),
    (dict(basis=torch.full((2, 20), float("nan"), dtype=DT)), "basis"),
    (dict(basis=torch.ones(2, 10, dtype=DT)), "basis"),
    (dict(basis=torch.ones(2, 20, dtype=DT), materials=None), "materials"),
    (dict(basis=torch.ones(2, 20, dtype=DT), materials="auto"), "materials"),
    (dict(basis=torch.ones(2, 20, dtype=DT), robust_scale=-1.0), "robust_scale"),
    (dict(robust_scale=1.0), "robust_scale"),
])
def test_given_basis_arguments_are_validated(kw, name):
    img, l, _ = _scene(p=10, l=8)
    with pytest.raises(ValueError, match=name):
        ps.solve_hsh(img, l, **kw)


def test_float32_images_are_held_in_float32():
    img, l, _ = _scene(p=40, l=12, seed=11)
    d = prepare_inputs(img.float(), l.float(), dtype=torch.float64)
    assert d.y.dtype == torch.float32 and d.dtype == torch.float64 and d.lights.dtype == torch.float64
    assert math.isclose(float(d.y.abs().max()), float((img.float()).abs().max()), rel_tol=1e-6)


def test_result_save_and_load_round_trip(tmp_path):
    img, l, _ = _scene(p=48, l=16, seed=12)
    r = ps.solve_hsh(img.reshape(16, 6, 8, 3), l, **FAST)
    f = tmp_path / "res.npz"
    r.write(f)
    with pytest.raises(FileExistsError):
        r.write(f)
    q = ps.HSHResult.read(f)
    for name in ("normals", "coefficients", "albedo", "residual", "mask", "lights", "confidence", "basis_brdfs",
                 "mixing"):
        assert torch.equal(getattr(q, name), getattr(r, name)), name
    assert q.order == r.order and q.weights.shape == (6, 8, 0)
    assert q.info["materials"] == r.info["materials"]
    r.write(f, weights=True, overwrite=True)
    assert torch.equal(ps.HSHResult.read(f).weights, r.weights)
    assert torch.allclose(q.relight(l[:2]), r.relight(l[:2]))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        ps.HSHResult.read(bad)
    # other files of a result folder, and a truncated archive: a ValueError that names the file, never numpy's
    # TypeError of a .npy under `with` or its advice to load pickled data unsafely
    import numpy as np

    np.save(tmp_path / "normals.npy", r.normals.numpy())
    (tmp_path / "metrics.json").write_text('{"pixels": 48}')
    (tmp_path / "cut.npz").write_bytes(f.read_bytes()[:200])
    for name in ("normals.npy", "metrics.json", "cut.npz"):
        with pytest.raises(ValueError, match=rf"{name}: not a saved HSHResult") as e:
            ps.HSHResult.read(tmp_path / name)
        assert "allow_pickle" not in str(e.value)


def _npy_with_header(header: str, data: bytes = b"") -> bytes:
    """A version 1.0 ``.npy`` member with ``header`` (the dict text) as written, padded as numpy pads it."""
    import struct

    text = header.encode("latin1")
    text += b" " * (-(10 + len(text) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + data


def _rezipped(src, dst, **members):
    """``src`` (an .npz) copied to ``dst`` with the ``name.npy`` members of ``members`` replaced (None: removed)."""
    import zipfile

    with zipfile.ZipFile(src) as zi, zipfile.ZipFile(dst, "w") as zo:
        for name in zi.namelist():
            new = members.get(name[:-4], zi.read(name))
            if new is not None:
                zo.writestr(name, new)
    return dst


def test_result_read_refuses_corrupt_archives_naming_the_file(tmp_path):
    import io
    import json

    import numpy as np

    g = torch.Generator().manual_seed(0)
    S = (3, 4)
    r = ps.HSHResult(normals=torch.nn.functional.normalize(torch.randn(*S, 3, generator=g), dim=-1),
                     coefficients=torch.randn(*S, 3, 20, generator=g), albedo=torch.rand(*S, 3, generator=g),
                     residual=torch.rand(*S, generator=g), weights=torch.zeros(*S, 0), mask=torch.ones(*S, dtype=torch.bool),
                     order=3, lights=torch.tensor([[0.0, 0.0, 1.0]] * 5), runtime_s=0.5)
    good = tmp_path / "good.npz"
    r.write(good)
    assert ps.HSHResult.read(good).normals.shape == S + (3,)

    def meta(text: str) -> bytes:
        buf = io.BytesIO()
        np.save(buf, np.frombuffer(text.encode(), dtype=np.uint8))
        return buf.getvalue()

    ok_meta = json.dumps({"format": "torch_hsh.HSHResult", "version": 1, "order": 3})
    cases = {  # without the checks: MemoryError, AttributeError, RecursionError, KeyError, TokenError, a wrong result
        "huge": (dict(normals=_npy_with_header("{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000, 3), }")),
                 r"member normals\.npy claims 12000000000000 bytes"),
        "list": (dict(metadata=meta("[1, 2]")), r"not a saved HSHResult \(format 'list'\)"),
        "deep": (dict(metadata=meta("[" * 100000)), r"not a saved HSHResult \(RecursionError"),
        "order": (dict(metadata=meta(ok_meta.replace("3", '"3"'))), r"corrupt HSHResult metadata"),
        "missing": (dict(normals=None), r"not a saved HSHResult \(no normals\)"),
        "shape": (dict(albedo=meta("x")), r"corrupt HSHResult: albedo is uint8 \(\d+,\), expected float \(3, 4, \*\)"),
        "pixels": (dict(albedo=_npy_with_header("{'descr': '<f8', 'fortran_order': False, 'shape': (2, 4, 3), }",
                                                bytes(192))), r"corrupt HSHResult: albedo is float64 \(2, 4, 3\), expected float \(3, 4, \*\)"),
        "token": (dict(normals=_npy_with_header("{'descr': '<f4', 'shape': (3,")), r"not a saved HSHResult \(TokenError"),
    }
    for name, (members, msg) in cases.items():
        f = _rezipped(good, tmp_path / f"{name}.npz", **members)
        with pytest.raises(ValueError, match=rf"{name}\.npz: {msg}"):
            ps.HSHResult.read(f)


def test_refinement_passes_restart_from_the_refined_normals():
    img, l, n = _scene(p=200, l=24, seed=3)
    one = ps.solve_hsh(img, l, refinement_passes=1, **FAST)
    two = ps.solve_hsh(img, l, refinement_passes=2, **FAST)
    assert two.info["refinement_passes"] == 2.0
    assert torch.equal(one.basis_brdfs, two.basis_brdfs)  # the calibration is the same
    # the second pass is the first pass restarted from its own normals with the same basis and scale
    again = ps.solve_hsh(img, l, basis=one.basis_brdfs, robust_scale=one.info["robust_scale"], init=one.normals,
                         refinement_passes=1, **FAST)
    assert torch.allclose(two.normals, again.normals, atol=1e-6)
    for bad in (0, 6, 1.5, True):
        with pytest.raises(ValueError, match="refinement_passes"):
            ps.solve_hsh(img, l, refinement_passes=bad)
