"""Tests for torch_hsh.rti.io: .lp files, RTI capture folders (8-bit photographs, sRGB), and
``torch-hsh ps CAPTURE`` on such a folder. Small synthetic scenes only."""
import numpy as np
import pytest
import torch

from torch_hsh import cli, ps

from torch_hsh.render import scenes
from torch_hsh.brdf import BlinnPhong
from torch_hsh.rti.io import (
    find_lp,
    is_rti_folder,
    load_rti,
    read_image,
    read_lp,
    save_rti,
    srgb_decode,
    srgb_encode,
    write_lp,
)
from torch_hsh.render import render


def _scene(size=20, n=10, seed=0):
    normals, mask = scenes.sphere_normals(size, radius=0.9, dtype=torch.float64)
    lights = scenes.diligent_like_lights(n, seed=seed, dtype=torch.float64)
    ones = torch.ones(size, size, 1, dtype=torch.float64)
    model = BlinnPhong(albedo=0.6 * ones.expand(-1, -1, 3), specular=0.2 * ones, shininess=20.0 * ones)
    imgs = render(normals, lights, model) * mask[None, ..., None]
    return imgs, lights, mask, normals


def test_lp_roundtrip_comments_paths(tmp_path):
    (tmp_path / "sub").mkdir()
    lp = tmp_path / "a.lp"
    lp.write_text("# RTIBuilder export\n3\n\nimg 1.jpg 0 0 2\n# comment\nsub/b.jpg 0.6 0.0 0.8\n"
                  f"{tmp_path / 'c.jpg'} -0.6 0 0.8\n")
    names, paths, lights = read_lp(lp)
    assert names == ["img 1.jpg", "sub/b.jpg", str(tmp_path / "c.jpg")]
    assert paths == [tmp_path / "img 1.jpg", tmp_path / "sub" / "b.jpg", tmp_path / "c.jpg"]
    np.testing.assert_allclose(lights, [[0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8]])
    # an absolute Windows path from another machine falls back to the base name beside the .lp
    lp.write_text("1\nC:\\Users\\me\\capture\\x.jpg 0 0 1\n")
    assert read_lp(lp)[1] == [tmp_path / "x.jpg"]
    out = write_lp(tmp_path / "w.lp", ["a.png", "b.png"], [[0, 0, 3.0], [0.3, 0.4, 0.866]])
    n2, _, l2 = read_lp(out)
    assert n2 == ["a.png", "b.png"] and abs(l2[0, 2] - 1) < 1e-9
    with pytest.raises(FileExistsError):
        write_lp(out, ["a.png"], [[0, 0, 1.0]])


@pytest.mark.parametrize("text, msg", [
    ("3\na.jpg 0 0 1\nb.jpg 0 0.6 0.8\n", "line 1: the count says 3 images but 2"),
    ("1\na.jpg 0 0 1\nb.jpg 0 0.6 0.8\n", "line 3 is one too many"),
    ("2\na.jpg 0 0 1\nb.jpg 0 0 0\n", "line 3: zero light vector"),
    ("2\na.jpg 0 0 1\nb.jpg 0 x 1\n", "line 3: the light direction is not three numbers"),
    ("1\na.jpg 0 nan 1\n", "line 2: non-finite"),
    ("1\na.jpg 0 1\n", "line 2: expected 'filename lx ly lz'"),
    ("two\na.jpg 0 0 1\n", "line 1: expected the number of images"),
    ("1\na.jpg 0.6 0 -0.8\n", "line 2: light below the horizon"),
    ("# only a comment\n", "empty .lp file"),
    ("1\n" + "a" * 300 + ".jpg 0 0 1\n", "line 2: image name 'aaa"),  # the OS's limit: 255 bytes a part
])
def test_lp_errors_name_file_and_line(tmp_path, text, msg):
    lp = tmp_path / "bad.lp"
    lp.write_text(text)
    with pytest.raises(ValueError) as e:
        read_lp(lp)
    assert str(e.value).startswith(str(lp)) and msg in str(e.value)


def test_zero_vector_allowed_when_directions_are_not_checked(tmp_path):
    lp = tmp_path / "x.lp"
    lp.write_text("2\na.jpg 0 0 0\nb.jpg 0 0 1\n")
    names, _, lights = read_lp(lp, check_directions=False)
    assert names == ["a.jpg", "b.jpg"] and not lights[0].any()


def test_srgb_pair_is_inverse():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    assert abs(float(srgb_decode(np.array(0.5))) - 0.21404) < 1e-4


@pytest.mark.parametrize("fmt", ["png", "tif", "jpg"])
def test_save_load_roundtrip_srgb(tmp_path, fmt):
    imgs, lights, mask, _ = _scene()
    save_rti(tmp_path / "cap", imgs, lights, mask=mask, fmt=fmt)
    assert is_rti_folder(tmp_path / "cap") and find_lp(tmp_path / "cap").name == "lights.lp"
    d = load_rti(tmp_path / "cap", dtype=torch.float64)
    ref = imgs / imgs.max()
    assert d.images.shape == imgs.shape and torch.equal(d.mask, mask)
    torch.testing.assert_close(d.lights, lights, atol=2e-6, rtol=0)
    err = (d.images - ref).abs()
    # 8-bit sRGB codes: half a code step of the sRGB curve (largest near 1: 0.5/255 * 2.4 / 1.055 ~ 0.0045)
    tol = 0.006 if fmt != "jpg" else 0.05
    assert float(err.max()) < tol
    # --linear keeps the codes: visibly different from the decoded images
    d_lin = load_rti(tmp_path / "cap", linear=True, dtype=torch.float64)
    assert float((d_lin.images - d.images).abs().max()) > 0.1


def test_linear_write_and_read(tmp_path):
    imgs, lights, mask, _ = _scene()
    save_rti(tmp_path / "cap", imgs, lights, mask=mask, linear=True)
    d = load_rti(tmp_path / "cap", linear=True, dtype=torch.float64)
    assert float((d.images - imgs / imgs.max()).abs().max()) <= 0.5 / 255 + 1e-9


def test_missing_image_mixed_sizes_and_undecodable(tmp_path):
    imgs, lights, mask, _ = _scene()
    cap = save_rti(tmp_path / "cap", imgs, lights, mask=mask)
    (cap / "img_004.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"lights.lp: image 'img_004.png' \(number 4\) not found"):
        load_rti(cap)
    from PIL import Image

    Image.fromarray(np.zeros((7, 9, 3), np.uint8)).save(cap / "img_004.png")
    with pytest.raises(ValueError, match=r"img_004.png: image size 9x7 \(WxH\) differs"):
        load_rti(cap)
    from torch_hsh.io.diligent import _write_png

    _write_png(cap / "img_004.png", np.zeros((20, 20, 3), np.uint16))
    with pytest.raises(ValueError, match=r"img_004.png: bit depth 16 differs from the first image's 8 \(img_001.png\)"):
        load_rti(cap)
    (cap / "img_004.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(ValueError, match="img_004.png"):
        load_rti(cap)
    (cap / "img_004.png").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="img_004.png: cannot decode"):
        read_image(cap / "img_004.png")


def test_mask_optional_and_checked(tmp_path):
    imgs, lights, mask, _ = _scene()
    cap = save_rti(tmp_path / "cap", imgs, lights)
    with pytest.warns(UserWarning, match="no mask.png"):
        d = load_rti(cap)
    assert bool(d.mask.all())
    from torch_hsh.io.diligent import _write_png

    _write_png(tmp_path / "m.png", np.full((5, 5), 255, np.uint8))
    with pytest.raises(ValueError, match=r"m.png: mask size"):
        load_rti(cap, mask=tmp_path / "m.png")


def test_several_lp_files_need_a_choice(tmp_path):
    imgs, lights, mask, _ = _scene()
    cap = save_rti(tmp_path / "cap", imgs, lights, mask=mask)
    (cap / "other.lp").write_text((cap / "lights.lp").read_text())
    with pytest.raises(ValueError, match="several .lp files"):
        load_rti(cap)
    assert load_rti(cap / "other.lp").num_images == imgs.shape[0]


def test_ps_cli_accepts_an_rti_folder(tmp_path, capsys, monkeypatch):
    imgs, lights, mask, normals = _scene(size=16, n=12)
    cap = save_rti(tmp_path / "cap", imgs, lights, mask=mask)
    seen = {}

    def solve(images, lights, intensities=None, mask=None, **kw):
        seen["images"] = images
        lam = ps.lambertian_ls(images, lights, intensities, mask)
        return ps.HSHResult(normals=lam.normals, coefficients=torch.zeros(*mask.shape, 3, 4),
                                albedo=lam.albedo, residual=torch.zeros(mask.shape), weights=torch.zeros(*mask.shape, 0),
                                mask=mask, order=1, lights=lights, runtime_s=0.0)

    monkeypatch.setattr(ps, "solve_hsh", solve)
    metrics = cli.main(["ps", str(cap), "--out", str(tmp_path / "res"), "--quiet"])
    assert metrics == 0
    assert (tmp_path / "res" / "normals.npy").is_file()
    got = seen["images"]
    assert got.shape == imgs.shape
    torch.testing.assert_close(got.double(), imgs / imgs.max(), atol=0.006, rtol=0)
    lam = np.load(tmp_path / "res" / "normals.npy")
    cos = (torch.as_tensor(lam).double() * normals).sum(-1)[mask & (normals[..., 2] > 0.5)]
    assert float(torch.rad2deg(torch.arccos(cos.clamp(max=1))).mean()) < 10  # sRGB removed: sensible normals
    # --linear reaches the reader (codes are then not linearised)
    cli.main(["ps", str(cap), "--out", str(tmp_path / "res2"), "--quiet", "--linear-input"])
    assert float((seen["images"].double() - got.double()).abs().max()) > 0.1
    # too few images left by --drop-first is the options' doing (exit 2), not the .lp file's
    with pytest.raises(SystemExit) as e:
        cli.main(["ps", str(cap), "--out", str(tmp_path / "res3"), "--quiet",
                  "--drop-first", str(len(imgs) - 2)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--drop-first/--max-images" in err and f"2 of its {len(imgs)} images left" in err, err


@pytest.mark.parametrize("case, msg", [
    ("missing", "img_002.png"), ("count", "lights.lp line 1"), ("zero", "lights.lp line 3: zero light vector"),
    ("mixed", "img_002.png: image size"),
])
def test_ps_cli_bad_rti_inputs_exit_1_naming_the_file(tmp_path, capsys, case, msg):
    imgs, lights, mask, _ = _scene(size=12, n=6)
    cap = save_rti(tmp_path / "cap", imgs, lights, mask=mask)
    lp = cap / "lights.lp"
    lines = lp.read_text().splitlines()
    if case == "missing":
        (cap / "img_002.png").unlink()
    elif case == "count":
        lp.write_text("\n".join(["7"] + lines[1:]) + "\n")
    elif case == "zero":
        lines[2] = "img_002.png 0 0 0"
        lp.write_text("\n".join(lines) + "\n")
    else:
        from PIL import Image

        Image.fromarray(np.zeros((5, 5, 3), np.uint8)).save(cap / "img_002.png")
    with pytest.raises(SystemExit) as e:
        cli.main(["ps", str(cap), "--out", str(tmp_path / "res"), "--quiet"])
    assert e.value.code == 1
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err
    assert not (tmp_path / "res").exists()


def _tiff_with_size(path, width, height):
    """A 16-bit grey TIFF whose ImageWidth / ImageLength tags are overwritten (the pixels stay 4 x 3)."""
    import struct

    from PIL import Image

    Image.fromarray(np.zeros((3, 4), np.uint16)).save(path)
    d = bytearray(path.read_bytes())
    ifd = struct.unpack("<I", d[4:8])[0]
    for k in range(struct.unpack("<H", d[ifd:ifd + 2])[0]):
        e = ifd + 2 + 12 * k
        tag, typ = struct.unpack("<HH", d[e:e + 4])
        if tag in (256, 257):
            v = width if tag == 256 else height
            d[e + 8:e + 12] = struct.pack("<HH", v, 0) if typ == 3 else struct.pack("<I", v)
    path.write_bytes(bytes(d))


def test_read_image_refuses_a_header_larger_than_the_file(tmp_path):
    # 9000 x 9000 is below Pillow's decompression-bomb limit: without the check it decodes a 100-byte file into
    # hundreds of megabytes before finding it truncated
    from PIL import Image

    f = tmp_path / "big.jpg"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(f)
    d = bytearray(f.read_bytes())
    k = d.find(b"\xff\xc0")
    d[k + 5:k + 9] = (9000).to_bytes(2, "big") * 2
    f.write_bytes(bytes(d))
    with pytest.raises(ValueError, match=r"big\.jpg: the JPEG header claims 243000000 decoded bytes"):
        read_image(f)
    d[k + 5:k + 9] = (1500).to_bytes(2, "big") * 2  # 6.75 MB: far below Pillow's limit, far above what 700 bytes hold
    f.write_bytes(bytes(d))
    with pytest.raises(ValueError, match=r"big\.jpg: the JPEG header claims 6750000 decoded bytes"):
        read_image(f)
    _tiff_with_size(tmp_path / "big.tif", 9000, 9000)
    with pytest.raises(ValueError, match=r"big\.tif: the TIFF header claims 486000000 decoded bytes"):
        read_image(tmp_path / "big.tif")


def test_read_image_grey_16bit_tiff_rgba_png_and_grey_jpeg(tmp_path):
    from PIL import Image

    from torch_hsh.io.diligent import _write_png

    a16 = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    Image.fromarray(a16).save(tmp_path / "g16.tif")
    img, bits = read_image(tmp_path / "g16.tif")
    assert bits == 16 and img.shape == (3, 4, 3)
    np.testing.assert_allclose(img[..., 1], a16 / 65535.0)
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 17
    _write_png(tmp_path / "a.png", rgba)
    img, bits = read_image(tmp_path / "a.png")
    assert bits == 8 and img.shape == (2, 3, 3) and abs(img[0, 0, 0] - 200 / 255) < 1e-12
    Image.fromarray(np.full((4, 4), 128, np.uint8)).save(tmp_path / "g.jpg", quality=100)
    img, bits = read_image(tmp_path / "g.jpg")
    assert bits == 8 and img.shape == (4, 4, 3) and abs(img.mean() - 128 / 255) < 2 / 255
