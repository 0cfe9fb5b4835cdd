"""Tests for torch_hsh.rti and the RTI subcommands: light directions from a rendered glossy sphere,
the RTI HSH basis, and the HSH RTI export (.rti, relight/OpenLIME) read back by an independent reader.

The reader below is written from the RTI viewers' published loaders and evaluation formulas
(RTIViewer ``UniversalRti::load`` / ``Hsh::loadData`` / ``getHSH``, relight ``LRti::loadHSH``,
OpenLIME ``ShaderRTI`` / ``HSH.lightWeights``), in NumPy, and does not use this library's basis code.
"""
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_hsh import cli, hsh
from torch_hsh.cli.result_folder import is_result_folder

from torch_hsh.render import scenes
from torch_hsh.brdf import BlinnPhong
from torch_hsh.io.diligent import _write_png, save_diligent
from torch_hsh.rti.io import read_lp, save_relight, save_rti, srgb_encode, write_rti_hsh
from torch_hsh.render import render, render_coefficients
from torch_hsh.rti import (
    OPENLIME_THETA_CLAMP,
    RTIVIEWER_THETA_CLAMP,
    evaluate_rti,
    fit_rti,
    project_to_rti,
    rti_hsh_basis,
    sphere_circle_from_mask,
    sphere_light_directions,
)


# --------------------------------------------------------------------------- #
# independent reader (viewers' formulas)
# --------------------------------------------------------------------------- #
def viewer_weights(light, terms, theta_max):
    """HSH weights as RTIViewer's getHSH / OpenLIME's HSH.lightWeights compute them for one light."""
    lx, ly, lz = np.asarray(light, float) / np.linalg.norm(light)
    phi = math.atan2(ly, lx)
    if phi < 0:
        phi += 2 * math.pi
    theta = min(math.acos(lz), theta_max)
    cP, cT = math.cos(phi), math.cos(theta)
    cT2 = cT * cT
    P = math.pi
    w = [1 / math.sqrt(2 * P),
         math.sqrt(6 / P) * (cP * math.sqrt(cT - cT2)),
         math.sqrt(3 / (2 * P)) * (-1 + 2 * cT),
         math.sqrt(6 / P) * (math.sqrt(cT - cT2) * math.sin(phi)),
         math.sqrt(30 / P) * (math.cos(2 * phi) * (-cT + cT2)),
         math.sqrt(30 / P) * (cP * (-1 + 2 * cT) * math.sqrt(cT - cT2)),
         math.sqrt(5 / (2 * P)) * (1 - 6 * cT + 6 * cT2),
         math.sqrt(30 / P) * ((-1 + 2 * cT) * math.sqrt(cT - cT2) * math.sin(phi)),
         math.sqrt(30 / P) * ((-cT + cT2) * math.sin(2 * phi))]
    if terms > 9:
        w += [2 * math.sqrt(35 / P) * (math.cos(3 * phi) * (cT - cT2) ** 1.5),
              math.sqrt(210 / P) * (math.cos(2 * phi) * (-1 + 2 * cT) * (-cT + cT2)),
              2 * math.sqrt(21 / P) * (math.cos(phi) * math.sqrt(cT - cT2) * (1 - 5 * cT + 5 * cT2)),
              math.sqrt(7 / (2 * P)) * (-1 + 12 * cT - 30 * cT2 + 20 * cT2 * cT),
              2 * math.sqrt(21 / P) * (math.sqrt(cT - cT2) * (1 - 5 * cT + 5 * cT2) * math.sin(phi)),
              math.sqrt(210 / P) * (-1 + 2 * cT) * (-cT + cT2) * math.sin(2 * phi),
              2 * math.sqrt(35 / P) * (cT - cT2) ** 1.5 * math.sin(3 * phi)]
    return np.array(w)


def read_rti_file(path):
    """(H, W, 3, T) coefficients of an HSH .rti file, as RTIViewer's UniversalRti::load reads it."""
    data = open(path, "rb").read()
    pos = 0
    lines = []
    while len(lines) < 3:
        end = data.index(b"\n", pos)
        line = data[pos:end].decode("ascii").strip()
        pos = end + 1
        if line.startswith("#"):
            continue
        lines.append(line)
    assert int(lines[0]) == 3  # HSH
    w, h, ncol = (int(v) for v in lines[1].split())
    terms, _basis_type, _elem = (int(v) for v in lines[2].split())
    assert ncol == 3
    scale = struct.unpack(f"<{terms}f", data[pos: pos + 4 * terms])
    bias = struct.unpack(f"<{terms}f", data[pos + 4 * terms: pos + 8 * terms])
    pos += 8 * terms
    raw = np.frombuffer(data, dtype=np.uint8, count=w * h * 3 * terms, offset=pos)
    assert pos + raw.size == len(data)
    c = raw.reshape(h, w, 3, terms) / 255.0 * np.array(scale, np.float32) + np.array(bias, np.float32)
    return c, np.array(scale)


def read_relight(folder):
    """(H, W, 3, 9) coefficients of a relight/OpenLIME HSH folder, as OpenLIME's RGB shader dequantises them."""
    from PIL import Image

    info = json.loads((folder / "info.json").read_text())
    assert info["type"] == "hsh" and info["colorspace"] == "rgb" and info["nplanes"] == 27
    scale = np.array(info["materials"][0]["scale"])
    bias = np.array(info["materials"][0]["bias"])
    planes = []
    for j in range(info["nplanes"] // 3):
        img = np.asarray(Image.open(folder / f"plane_{j}.{info['format']}").convert("RGB")) / 255.0
        assert img.shape[:2] == (info["height"], info["width"])
        planes.append((img - bias[3 * j: 3 * j + 3]) * scale[3 * j: 3 * j + 3])
    return np.stack(planes, axis=-1), scale.reshape(9, 3).T


def viewer_relight(coefficients, light, theta_max):
    return coefficients @ viewer_weights(light, coefficients.shape[-1], theta_max)


# --------------------------------------------------------------------------- #
# scenes
# --------------------------------------------------------------------------- #
def glossy_sphere(size=96, lights=None, seed=0):
    n, m = scenes.sphere_normals(size, radius=0.8, dtype=torch.float64)
    if lights is None:
        lights = scenes.cone_lights(24, max_angle_deg=70.0, seed=seed, dtype=torch.float64)
    one = torch.ones(size, size, 1, dtype=torch.float64)
    img = render(n, lights, BlinnPhong(0.05 * one.expand(-1, -1, 3), one, 400 * one)) * m[None, ..., None]
    return img, lights, m


def angles(est, lights):
    c = (torch.as_tensor(est) * lights).sum(-1).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(c))


def test_circle_from_mask_matches_the_scene_sphere():
    _, m = scenes.sphere_normals(80, radius=0.75)
    cx, cy, r = sphere_circle_from_mask(m)
    assert abs(cx - 39.5) < 1e-9 and abs(cy - 39.5) < 1e-9 and abs(r - 30.0) < 0.2
    with pytest.raises(ValueError, match="no sphere found"):
        sphere_circle_from_mask(torch.zeros(8, 8, dtype=torch.bool))


@pytest.mark.parametrize("use_mask", [False, True])
def test_sphere_lights_clean_below_one_degree(use_mask):
    img, lights, m = glossy_sphere()
    est = sphere_light_directions(img, mask=m) if use_mask else sphere_light_directions(img, circle=(47.5, 47.5, 38.4))
    e = angles(est.lights, lights)
    assert est.found.all() and float(e.max()) < 1.0, e


def test_sphere_lights_degrade_gracefully_with_noise_and_saturation():
    img, lights, m = glossy_sphere()
    g = torch.Generator().manual_seed(0)
    noisy = img + 0.02 * img.max() * torch.randn(img.shape, generator=g, dtype=img.dtype)
    assert float(angles(sphere_light_directions(noisy, mask=m).lights, lights).mean()) < 1.0
    clipped = img.clamp(max=0.05 * float(img.max()))
    est = sphere_light_directions(clipped, mask=m)
    assert (est.saturated > 1).all() and float(angles(est.lights, lights).mean()) < 1.0
    codes = np.rint(srgb_encode((img / img.max()).numpy()) * 255) / 255  # an 8-bit sRGB photograph
    assert float(angles(sphere_light_directions(codes, mask=m).lights, lights).max()) < 1.0


def test_no_highlight_and_bad_circle_are_errors():
    img, lights, m = glossy_sphere(48)
    dark = img.clone()
    dark[3] = 0.0
    with pytest.raises(ValueError, match="image 3: no highlight found"):
        sphere_light_directions(dark, mask=m)
    est = sphere_light_directions(dark, mask=m, on_missing="keep")
    assert not est.found[3] and est.found.sum() == len(lights) - 1 and not est.lights[3].any()
    with pytest.raises(ValueError, match="not inside"):
        sphere_light_directions(img, circle=(40, 24, 19))


def test_lights_cli_rti_and_diligent_folders(tmp_path, capsys):
    img, lights, m = glossy_sphere(64)
    cap = save_rti(tmp_path / "cap", img, torch.tensor([[0.0, 0.0, 1.0]]).expand(len(lights), 3), mask=m)
    _write_png(tmp_path / "sphere.png", m.numpy().astype(np.uint8) * 255)
    out = tmp_path / "est.lp"
    assert cli.main(["lights", str(cap), "--sphere-mask", str(tmp_path / "sphere.png"), "--out", str(out),
                     "--quiet"]) == 0
    names, paths, est = read_lp(out)
    assert paths == [cap / f"img_{i + 1:03d}.png" for i in range(len(lights))]
    assert float(angles(est, lights).max()) < 1.0
    # without --out: CAPTURE.lp beside the folder, which `torch-hsh ps CAPTURE.lp` reads
    assert cli.main(["lights", str(cap), "--sphere-mask", str(tmp_path / "sphere.png"), "--quiet"]) == 0
    assert read_lp(tmp_path / "cap.lp")[1] == [cap / f"img_{i + 1:03d}.png" for i in range(len(lights))]
    out2 = cap / "est.lp"
    assert cli.main(["lights", str(cap), "--sphere-circle", "31.5", "31.5", "25.6", "--out", str(out2),
                     "--quiet"]) == 0
    assert read_lp(out2)[0][0] == "img_001.png"  # relative to the .lp folder
    # a DiLiGenT folder (16-bit PNGs, filenames.txt)
    save_diligent(tmp_path / "dil", img, lights, mask=m)
    out3 = tmp_path / "dil.lp"
    assert cli.main(["lights", str(tmp_path / "dil"), "--sphere-mask", str(tmp_path / "dil" / "mask.png"),
                     "--out", str(out3), "--quiet"]) == 0
    assert float(angles(read_lp(out3)[2], lights).max()) < 1.0


def test_lights_cli_exit_codes(tmp_path, capsys):
    img, lights, m = glossy_sphere(40)
    img[2] = 0.0
    cap = save_rti(tmp_path / "cap", img, lights, mask=m)
    out = str(tmp_path / "o.lp")

    def run(*argv):
        with pytest.raises(SystemExit) as e:
            cli.main(["lights", str(cap), *argv, "--out", out, "--quiet"])
        return e.value.code, capsys.readouterr().err

    code, err = run("--sphere-circle", "30", "20", "15")
    assert code == 2 and "not inside the 40x40 images" in err
    code, err = run("--sphere-circle", "20", "20", "15")
    assert code == 1 and "no highlight found" in err and "img_003.png" in err
    # a circle smaller than the sphere puts the steepest lights' highlights beyond r / sqrt(2): below the horizon,
    # which `torch-hsh ps` would refuse, so nothing is written
    img_ok = img.clone()
    img_ok[2] = img_ok[1]
    cap_ok = save_rti(tmp_path / "cap_ok", img_ok, lights, mask=m)
    with pytest.raises(SystemExit) as e:
        cli.main(["lights", str(cap_ok), "--sphere-circle", "19.5", "19.5", "12", "--out", out, "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 1 and "at or below the horizon" in err and "cap_ok" in err, err
    assert cli.main(["lights", str(cap_ok), "--sphere-circle", "19.5", "19.5", "16", "--out", out, "--quiet"]) == 0
    Path(out).unlink()
    _write_png(tmp_path / "empty.png", np.zeros((40, 40), np.uint8))
    code, err = run("--sphere-mask", str(tmp_path / "empty.png"))
    assert code == 1 and "empty.png" in err and "no sphere found" in err
    (cap / "img_002.png").unlink()
    code, err = run("--sphere-circle", "20", "20", "15")
    assert code == 1 and "img_002.png" in err
    code, err = run()
    assert code == 2
    assert not (tmp_path / "o.lp").exists()


# --------------------------------------------------------------------------- #
# basis
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("terms", [9, 16])
def test_basis_matches_the_viewer_formulas_and_is_orthonormal(terms, hemi_quadrature):
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    d[:, 2] = d[:, 2].abs() + 0.05
    d = torch.nn.functional.normalize(d, dim=-1)
    ours = rti_hsh_basis(d, terms).numpy()
    ref = np.stack([viewer_weights(v, terms, math.pi / 2) for v in d.numpy()])
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    clamped = rti_hsh_basis(d, terms, theta_clamp=OPENLIME_THETA_CLAMP).numpy()
    np.testing.assert_allclose(clamped, np.stack([viewer_weights(v, terms, OPENLIME_THETA_CLAMP) for v in d.numpy()]),
                               atol=1e-12)
    dirs, w = hemi_quadrature(12, 16)
    B = rti_hsh_basis(dirs, terms)
    np.testing.assert_allclose((B * w[:, None]).T @ B, np.eye(terms), atol=1e-10)
    # each term is +- one of the library's hemispherical harmonics (a signed permutation)
    order = 2 if terms == 9 else 3
    M = torch.linalg.lstsq(hsh(dirs, order), B).solution
    np.testing.assert_allclose(M.abs().sum(0), np.ones(terms), atol=1e-8)
    np.testing.assert_allclose(M.abs().max(0).values, np.ones(terms), atol=1e-8)


def test_fit_rti_recovers_coefficients_and_checks_inputs():
    li = scenes.cone_lights(40, max_angle_deg=80.0, seed=2, dtype=torch.float64)
    c0 = torch.randn(3, 4, 3, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    c = fit_rti(evaluate_rti(c0, li), li, 16, ridge=0.0)
    torch.testing.assert_close(c, c0, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="at least 16 lights"):
        fit_rti(evaluate_rti(c0, li[:10]), li[:10], 16)
    with pytest.raises(ValueError, match="9 or 16"):
        rti_hsh_basis(li, 4)


# --------------------------------------------------------------------------- #
# export
# --------------------------------------------------------------------------- #
def material_scene(size=24):
    """Bumpy-free sphere with a textured Lambertian + Blinn-Phong model given as Helmholtz coefficient maps."""
    from torch_hsh.fitting import project

    n, m = scenes.sphere_normals(size, radius=0.9, dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    spec = project(BlinnPhong(albedo=0 * one, specular=one, shininess=20 * one), order=4, n_theta=24, n_phi=48)[0]
    K = spec.shape[0]
    albedo = 0.2 + 0.6 * scenes.albedo_texture(size, seed=0, dtype=torch.float64)  # (H, W, 3)
    a = torch.zeros(size, size, 3, K, dtype=torch.float64)
    a[..., 0] = 2.0 * albedo
    a = a + 0.4 * spec
    return n, m, a


def srgb(x):
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


TEST_LIGHTS = torch.tensor([[0.3, -0.2, 0.933], [-0.5, 0.4, 0.768], [0.1, 0.7, 0.707]], dtype=torch.float64)


@pytest.mark.parametrize("terms", [9, 16])
def test_rti_file_relights_like_the_projected_function(tmp_path, terms):
    n, m, a = material_scene()
    c = project_to_rti(n, a, terms, mask=m, exposure=0.9, nz=24, nphi=48)
    f = write_rti_hsh(tmp_path / "x.rti", c)
    got, scale = read_rti_file(f)
    assert got.shape == (24, 24, 3, terms)
    lib = evaluate_rti(c, TEST_LIGHTS).numpy()  # the library's evaluation of the projected function
    for j, li in enumerate(TEST_LIGHTS.numpy()):
        v = viewer_relight(got, li, RTIVIEWER_THETA_CLAMP)
        bound = np.abs(viewer_weights(li, terms, RTIVIEWER_THETA_CLAMP)) @ (scale / 510) + 1e-5
        assert np.abs(v - lib[j]).max() <= bound
    # the image is upright: the top rows of the file are the top of the object (normals with y > 0 lit from +y)
    top = viewer_relight(got[:8], [0, 0.8, 0.6], RTIVIEWER_THETA_CLAMP).mean()
    bottom = viewer_relight(got[-8:], [0, 0.8, 0.6], RTIVIEWER_THETA_CLAMP).mean()
    assert top > bottom
    with pytest.raises(FileExistsError):
        write_rti_hsh(f, c)


@pytest.mark.parametrize("fmt, tol", [("png", None), ("jpg", 0.03)])
def test_relight_folder_relights_like_the_projected_function(tmp_path, fmt, tol):
    n, m, a = material_scene()
    c = project_to_rti(n, a, 9, mask=m, exposure=0.9, nz=24, nphi=48)
    folder = save_relight(tmp_path / "r", c, fmt=fmt)
    got, scale = read_relight(folder)
    lib = evaluate_rti(c, TEST_LIGHTS).numpy()
    for j, li in enumerate(TEST_LIGHTS.numpy()):
        v = viewer_relight(got, li, OPENLIME_THETA_CLAMP)
        if tol is None:
            bound = (np.abs(viewer_weights(li, 9, OPENLIME_THETA_CLAMP)) * (scale / 510)).sum(-1) + 1e-6
            assert (np.abs(v - lib[j]) <= bound).all()
        else:
            assert np.sqrt(((v - lib[j])[m.numpy()] ** 2).mean()) < tol
    with pytest.raises(ValueError, match="9 HSH terms"):
        save_relight(tmp_path / "r16", project_to_rti(n, a, 16, mask=m, nz=8, nphi=16))


def test_projection_error_and_plain_fit_on_held_out_lights():
    """The numbers reported in the docs, at small size: projection vs full render, and held-out relighting."""
    n, m, a = material_scene()
    exposure = 0.9
    train = scenes.diligent_like_lights(40, seed=3, dtype=torch.float64)
    test = scenes.diligent_like_lights(12, seed=4, dtype=torch.float64)
    full = srgb(exposure * render_coefficients(n, test, a).clamp(min=0))[:, m]  # what a camera would record
    photos = torch.round(srgb(exposure * render_coefficients(n, train, a).clamp(min=0)) * 255) / 255
    cap = float(torch.rad2deg(torch.arccos(train[:, 2])).max())
    err = {}
    for terms in (9, 16):
        proj = evaluate_rti(project_to_rti(n, a, terms, mask=m, exposure=exposure), test)[:, m]
        capped = evaluate_rti(project_to_rti(n, a, terms, mask=m, exposure=exposure, max_angle_deg=cap), test)[:, m]
        plain = evaluate_rti(fit_rti(photos, train, terms, mask=m), test)[:, m]
        err[terms] = [float((x - full).pow(2).mean().sqrt()) for x in (proj, capped, plain)]
    # truncation leaves an error of a few percent of white; more terms help; fitting the cap of the
    # captured lights beats the whole-hemisphere projection on lights inside that cap
    assert err[16][0] < err[9][0] < 0.1 and err[16][1] < err[9][1]
    assert all(e[1] < e[0] and e[2] < 0.1 for e in err.values()), err
    with pytest.raises(ValueError, match="max_angle_deg"):
        project_to_rti(n, a, 9, max_angle_deg=95)
    with pytest.raises(TypeError, match="`linear` must be a bool"):
        project_to_rti(n, a, 9, linear="srgb")


def test_end_to_end_lights_ps_rti_commands(tmp_path, capsys):
    """An RTI capture rendered by the library: sphere lights -> photometric stereo -> .rti + relight export."""
    size = 20
    n, m = scenes.sphere_normals(size, radius=0.9, dtype=torch.float64)
    lights = scenes.cone_lights(16, max_angle_deg=60.0, seed=5, dtype=torch.float64)
    one = torch.ones(size, size, 1, dtype=torch.float64)
    obj = render(n, lights, BlinnPhong(0.7 * one.expand(-1, -1, 3), 0.2 * one, 15 * one)) * m[None, ..., None]
    sph, _, sm = glossy_sphere(size * 2, lights=lights)
    imgs = torch.zeros(len(lights), size * 2, size * 3, 3, dtype=torch.float64)  # object left, sphere right
    imgs[:, size // 2: size // 2 + size, :size] = obj / obj.max()
    imgs[:, :, size:] = 0.6 * sph / sph.max()
    mask = torch.zeros(imgs.shape[1:3], dtype=torch.bool)
    mask[size // 2: size // 2 + size, :size] = m
    smask = torch.zeros_like(mask)
    smask[:, size:] = sm
    cap = save_rti(tmp_path / "cap", imgs, torch.tensor([[0.0, 0.0, 1.0]]).expand(len(lights), 3), mask=mask)
    _write_png(tmp_path / "sphere.png", smask.numpy().astype(np.uint8) * 255)
    (cap / "lights.lp").unlink()
    (cap / "lights.lp").write_text("16\n" + "".join(f"img_{i + 1:03d}.png 0 0 1\n" for i in range(16)))
    assert cli.main(["lights", str(cap), "--sphere-mask", str(tmp_path / "sphere.png"), "--out",
                     str(cap / "lights.lp"), "--overwrite", "--quiet"]) == 0
    assert float(angles(read_lp(cap / "lights.lp")[2], lights).max()) < 1.0
    assert cli.main(["ps", str(cap), "--out", str(tmp_path / "res"), "--quiet", "--order", "2",
                     "--materials", "0"]) == 0
    assert cli.main(["rti", str(tmp_path / "res"), "--terms", "9", "--rti", str(tmp_path / "o.rti"),
                     "--relight", str(tmp_path / "o_relight"), "--quiet"]) == 0
    c, _ = read_rti_file(tmp_path / "o.rti")
    c2, _ = read_relight(tmp_path / "o_relight")
    assert c.shape == (size * 2, size * 3, 3, 9) and c2.shape == c.shape
    front = viewer_relight(c, [0, 0, 1], RTIVIEWER_THETA_CLAMP)
    assert front[mask.numpy()].mean() > 0.2 and np.abs(front[~mask.numpy()]).max() < 0.02
    # default: non-negative at every light within OpenLIME's clamp; --allow-negative: the plain fit;
    # --layout deepzoom: the same codes as Deep Zoom pyramids
    grazing = [[math.cos(p) * math.sin(t), math.sin(p) * math.sin(t), math.cos(t)]
               for t in np.radians([30, 60, 81]) for p in np.linspace(0, 2 * np.pi, 16, endpoint=False)]
    low = min(float(viewer_relight(c, li, OPENLIME_THETA_CLAMP).min()) for li in grazing)
    assert low > -0.02  # the 8-bit quantisation of the .rti, at most
    assert cli.main(["rti", str(tmp_path / "res"), "--rti", str(tmp_path / "neg.rti"), "--allow-negative",
                     "--relight", str(tmp_path / "dz"), "--layout", "deepzoom", "--quiet"]) == 0
    c3, _ = read_rti_file(tmp_path / "neg.rti")
    assert np.abs(c3 - c).max() > 0.01  # the constraint changed some pixels of this capture
    assert (tmp_path / "dz" / "plane_8.dzi").is_file() and (tmp_path / "dz" / "plane_8_files" / "0" / "0_0.jpg").is_file()
    with pytest.raises(SystemExit) as e:  # --layout is for the relight folder
        cli.main(["rti", str(tmp_path / "res"), "--rti", str(tmp_path / "q.rti"), "--layout", "deepzoom", "--quiet"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["rti", str(tmp_path / "res"), "--terms", "16", "--relight", str(tmp_path / "x"), "--quiet"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["rti", str(tmp_path / "res"), "--max-angle", "120", "--rti", str(tmp_path / "z.rti"), "--quiet"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["rti", str(tmp_path / "nothing"), "--rti", str(tmp_path / "y.rti"), "--quiet"])
    assert e.value.code == 1 and "nothing" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["rti", str(tmp_path / "res"), "--rti", str(tmp_path / "t.rti"), "--threads", "0", "--quiet"])
    assert e.value.code == 2 and "--threads: must be between 1 and 1024" in capsys.readouterr().err
    for opt in ("--rti", "--relight"):  # not into the result folder: the next `ps --out` there would refuse it
        with pytest.raises(SystemExit) as e:
            cli.main(["rti", str(tmp_path / "res"), opt, str(tmp_path / "res" / "o.rti"), "--quiet"])
        assert e.value.code == 2 and "is a torch-hsh ps result folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["view", str(tmp_path / "res"), "--out", str(tmp_path / "res" / "v.html"), "--quiet"])
    assert e.value.code == 2 and "is a torch-hsh ps result folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # nor the result folder itself as a --relight folder, even with --overwrite
        cli.main(["rti", str(tmp_path / "res"), "--relight", str(tmp_path / "res"), "--overwrite", "--quiet"])
    assert e.value.code == 2 and "is a torch-hsh ps result folder" in capsys.readouterr().err
    assert is_result_folder(tmp_path / "res")
    with pytest.raises(SystemExit) as e:  # a missing folder for the .rti file: an argument error, before the projection
        cli.main(["rti", str(tmp_path / "res"), "--rti", str(tmp_path / "no_dir" / "o.rti"), "--quiet"])
    assert e.value.code == 2 and "no_dir does not exist" in capsys.readouterr().err
    # a --relight folder is created with its parents
    assert cli.main(["rti", str(tmp_path / "res"), "--relight", str(tmp_path / "new" / "sub" / "rl"), "--quiet"]) == 0
    assert (tmp_path / "new" / "sub" / "rl" / "info.json").is_file()
    # neither --rti nor --relight: RESULT.rti beside the result; progress bars on stderr unless --quiet
    capsys.readouterr()
    assert cli.main(["rti", str(tmp_path / "res")]) == 0
    assert read_rti_file(tmp_path / "res.rti")[0].shape == c.shape
    assert "RTI projection" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # a file of the result folder that is not the result
        cli.main(["rti", str(tmp_path / "res" / "normals.npy"), "--rti", str(tmp_path / "y.rti"), "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 1 and "normals.npy: not a saved HSHResult" in err and "TypeError" not in err, err


def test_example_capture_and_lights_command(tmp_path):
    from _scripts import load_example

    mod = load_example("examples/rti_capture.py")
    out = tmp_path / "cap"
    mod.main(["--out", str(out), "--size", "48", "--lights", "12"])
    assert cli.main(["lights", str(out), "--sphere-mask", str(out / "sphere_mask.png"), "--out",
                     str(out / "lights.lp"), "--overwrite", "--quiet"]) == 0
    true = torch.as_tensor(np.loadtxt(out / "true_lights.txt"))
    assert float(angles(read_lp(out / "lights.lp")[2], true).max()) < 1.0
