"""Tests for torch_hsh.io.diligent (DiLiGenT folder layout, 16-bit PNG I/O)."""
import struct
import sys
import zlib

import numpy as np
import pytest
import scipy.io
import torch

from torch_hsh.io.diligent import (
    PhotometricDataset,
    _png_info,
    _read_png,
    _write_png,
    load_diligent,
    save_diligent,
)

L, H, W = 5, 6, 7


def _close(a, b, rtol=1e-7, atol=0.0):
    # numpy comparison: torch.testing.assert_close costs a multi-second torch.distributed import
    assert a.dtype == b.dtype, (a.dtype, b.dtype)
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=rtol, atol=atol)


# --------------------------------------------------------------------------- #
# fixtures
# --------------------------------------------------------------------------- #
def _lights(n, seed=0):
    g = np.random.default_rng(seed)
    v = g.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 1.0
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _handmade_folder(root, names=("b.png", "a.png", "c.png"), write_intens=True, write_mask=True, write_names=True):
    """A folder written without save_diligent: explicit 16-bit codes and DiLiGenT-style text."""
    n = len(names)
    root.mkdir(parents=True, exist_ok=True)
    g = np.random.default_rng(1)
    codes = g.integers(0, 65536, size=(n, H, W, 3), dtype=np.uint16)
    for name, c in zip(names, codes):
        _write_png(root / name, c)
    lights = _lights(n)
    # DiLiGenT style: scientific notation, several spaces, trailing blanks, a final empty line
    (root / "light_directions.txt").write_text(
        "".join("  ".join(f"{x:.8e}" for x in row) + "   \n" for row in lights) + "\n"
    )
    intens = 0.5 + g.random((n, 3))
    if write_intens:
        (root / "light_intensities.txt").write_text("".join(" ".join(f"{x:.8f}" for x in r) + "\n" for r in intens))
    if write_names:
        (root / "filenames.txt").write_text("".join(s + "\n" for s in names))
    mask = g.random((H, W)) > 0.3
    if write_mask:
        _write_png(root / "mask.png", (mask * 255).astype(np.uint8))
    normals = g.normal(size=(H, W, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    scipy.io.savemat(str(root / "Normal_gt.mat"), {"Normal_gt": normals})
    return dict(codes=codes, lights=lights, intens=np.round(intens, 8), mask=mask, normals=normals, names=list(names))


def _random_scene(seed=0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(L, H, W, 3, generator=g, dtype=torch.float64) * 3.0
    lights = torch.as_tensor(_lights(L, seed))
    intens = 0.5 + torch.rand(L, 3, generator=g, dtype=torch.float64)
    mask = torch.rand(H, W, generator=g) > 0.4
    normals = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=g, dtype=torch.float64), dim=-1)
    return images, lights, intens, mask, normals


# --------------------------------------------------------------------------- #
# PNG codec
# --------------------------------------------------------------------------- #
def _paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    if pa <= pb and pa <= pc:
        return a
    return b if pb <= pc else c


def _encode_all_filters(img):
    """Independent reference PNG encoder cycling filter types 0..4 row by row (byte loops)."""
    h, w, ch = img.shape
    depth = 16 if img.dtype == np.uint16 else 8
    bpp = ch * depth // 8
    rows = (img.astype(">u2") if depth == 16 else img).view(np.uint8).reshape(h, w * bpp).astype(int)
    out = bytearray()
    prev = [0] * (w * bpp)
    for r in range(h):
        ftype = r % 5
        cur = rows[r].tolist()
        out.append(ftype)
        for i, x in enumerate(cur):
            a = cur[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            pred = [0, a, b, (a + b) // 2, _paeth(a, b, c)][ftype]
            out.append((x - pred) & 0xFF)
        prev = cur
    ctype = {1: 0, 3: 2, 4: 6}[ch]

    def chunk(t, body):
        return struct.pack(">I", len(body)) + t + body + struct.pack(">I", zlib.crc32(t + body) & 0xFFFFFFFF)

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(bytes(out)))
        + chunk(b"IEND", b"")
    )


def _decode_reference(data):
    """Independent PNG decoder for non-interlaced grey/RGB/RGBA 8/16-bit (byte loops; small images only)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat = 8, b""
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        t, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if t == b"IHDR":
            w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", body)
        elif t == b"IDAT":
            idat += body
        pos += 12 + n
    assert interlace == 0
    ch = {0: 1, 2: 3, 6: 4}[ctype]
    bpp = ch * depth // 8
    raw = zlib.decompress(idat)
    stride = w * bpp
    prev, out = [0] * stride, []
    for r in range(h):
        ftype, line = raw[r * (stride + 1)], raw[r * (stride + 1) + 1 : (r + 1) * (stride + 1)]
        cur = []
        for i, x in enumerate(line):
            a = cur[i - bpp] if i >= bpp else 0
            b, c = prev[i], (prev[i - bpp] if i >= bpp else 0)
            cur.append((x + [0, a, b, (a + b) // 2, _paeth(a, b, c)][ftype]) & 0xFF)
        out.append(cur)
        prev = cur
    arr = np.asarray(out, dtype=np.uint8)
    img = arr.view(">u2").astype(np.uint16) if depth == 16 else arr
    return img.reshape(h, w, ch)


@pytest.mark.parametrize("dtype,ch", [(np.uint16, 3), (np.uint8, 3), (np.uint16, 1), (np.uint8, 4)])
def test_png_reader_all_filter_types(tmp_path, dtype, ch):
    g = np.random.default_rng(0)
    img = g.integers(0, np.iinfo(dtype).max + 1, size=(11, 6, ch)).astype(dtype)
    f = tmp_path / "f.png"
    f.write_bytes(_encode_all_filters(img))
    dec = _read_png(f)
    assert dec.dtype == dtype
    np.testing.assert_array_equal(dec, img[..., 0] if ch == 1 else img)


@pytest.mark.parametrize("dtype,ch", [(np.uint16, 3), (np.uint16, 1), (np.uint8, 1), (np.uint8, 4)])
def test_png_writer_bit_exact(tmp_path, dtype, ch):
    img = np.random.default_rng(2).integers(0, np.iinfo(dtype).max + 1, size=(9, 13, ch)).astype(dtype)
    f = tmp_path / "x.png"
    _write_png(f, img[..., 0] if ch == 1 else img)
    assert _png_info(f)[:4] == (13, 9, 8 * np.dtype(dtype).itemsize, {1: 0, 3: 2, 4: 6}[ch])
    np.testing.assert_array_equal(_decode_reference(f.read_bytes()), img)  # independent decoder
    np.testing.assert_array_equal(_read_png(f), img[..., 0] if ch == 1 else img)


def test_png_reader_rejects_non_png(tmp_path):
    f = tmp_path / "x.png"
    f.write_bytes(b"not a png at all, definitely not a png")
    with pytest.raises(ValueError, match="not a PNG"):
        _read_png(f)


def test_png_reader_truncated_file_names_it(tmp_path):
    img = np.random.default_rng(3).integers(0, 65536, size=(40, 30, 3)).astype(np.uint16)
    f = tmp_path / "trunc.png"
    _write_png(f, img)
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"trunc\.png: cannot decode the 16-bit PNG"):
        _read_png(f)


def test_png_reader_refuses_a_header_larger_than_the_file_before_decoding(tmp_path, monkeypatch):
    import torch_hsh.io.diligent as dil

    f = tmp_path / "big.png"
    _write_png(f, np.zeros((4, 5, 3), np.uint16))
    d = bytearray(f.read_bytes())
    d[16:24] = struct.pack(">II", 20000, 20000)  # 2.4 GB of 16-bit RGB claimed by a 100-byte file
    d[29:33] = struct.pack(">I", zlib.crc32(bytes(d[12:29])) & 0xFFFFFFFF)
    f.write_bytes(bytes(d))
    monkeypatch.setattr(dil, "_kornia_rs_png", lambda *a: pytest.fail("decoded an unchecked header"))
    with pytest.raises(ValueError, match=r"big\.png: the PNG header claims 2400000000 decoded bytes"):
        _read_png(f)


def test_png_decoder_panic_is_a_value_error(tmp_path, monkeypatch):
    import torch_hsh.io.diligent as dil

    class PanicException(BaseException):  # pyo3's, raised by kornia-rs when an allocation fails
        pass

    def panic(path, mode):
        raise PanicException("PyObject pointer is null")

    f = tmp_path / "p.png"
    _write_png(f, np.zeros((4, 5, 3), np.uint16))
    monkeypatch.setattr(dil, "_kornia_rs_png", lambda *a: panic)
    with pytest.raises(ValueError, match=r"p\.png: cannot decode the 16-bit PNG \(PanicException"):
        _read_png(f)


def test_png_without_kornia_rs_fails_loudly(tmp_path, monkeypatch):
    f = tmp_path / "x.png"
    _write_png(f, np.zeros((4, 5, 3), np.uint16))
    monkeypatch.setitem(sys.modules, "kornia_rs", None)  # import kornia_rs -> ImportError
    with pytest.raises(ImportError, match="kornia-rs"):
        _read_png(f)
    with pytest.raises(ImportError, match="kornia-rs"):
        _write_png(tmp_path / "y.png", np.zeros((4, 5, 3), np.uint16))


def test_palette_and_grey_alpha_masks_via_pillow(tmp_path):
    from PIL import Image

    m = (np.arange(H * W).reshape(H, W) % 3).astype(np.uint8)
    im = Image.fromarray(m, "P")
    im.putpalette([0, 0, 0, 255, 255, 255, 10, 20, 30])
    im.save(tmp_path / "p.png")
    assert _png_info(tmp_path / "p.png")[3] == 3
    np.testing.assert_array_equal(_read_png(tmp_path / "p.png").max(-1) > 0, m > 0)
    Image.fromarray(np.stack([m * 100, m * 0 + 255], -1), "LA").save(tmp_path / "la.png")
    got = _read_png(tmp_path / "la.png")
    assert got.shape == (H, W, 2)
    np.testing.assert_array_equal(got[..., 0], m * 100)
    # load_diligent accepts such a mask
    _handmade_folder(tmp_path / "o")
    im.save(tmp_path / "o" / "mask.png")
    np.testing.assert_array_equal(load_diligent(tmp_path / "o").mask.numpy(), m > 0)


# --------------------------------------------------------------------------- #
# load_diligent
# --------------------------------------------------------------------------- #
def test_load_handmade_folder(tmp_path):
    ref = _handmade_folder(tmp_path / "obj")
    d = load_diligent(tmp_path / "obj", dtype=torch.float64)
    assert isinstance(d, PhotometricDataset)
    assert d.names == ref["names"]  # order of filenames.txt, not sorted
    assert d.images.shape == (3, H, W, 3) and d.images.dtype == torch.float64
    expected = ref["codes"] / 65535.0 / ref["intens"][:, None, None, :]
    np.testing.assert_allclose(d.images.numpy(), expected, rtol=1e-12)
    np.testing.assert_allclose(d.lights.numpy(), ref["lights"], atol=1e-8)
    np.testing.assert_allclose(torch.linalg.vector_norm(d.lights, dim=-1).numpy(), 1.0, atol=1e-15)
    np.testing.assert_allclose(d.intensities.numpy(), ref["intens"])
    np.testing.assert_array_equal(d.mask.numpy(), ref["mask"])
    assert d.mask.dtype == torch.bool
    np.testing.assert_array_equal(d.normals_gt.numpy(), ref["normals"])
    assert d.num_images == 3 and d.shape == (H, W)
    raw = load_diligent(tmp_path / "obj", normalize_intensities=False)
    assert raw.images.dtype == torch.float32
    np.testing.assert_allclose(raw.images.numpy(), ref["codes"] / 65535.0, rtol=1e-6)


def test_load_drop_first_and_max_images(tmp_path):
    ref = _handmade_folder(tmp_path / "o", names=("1.png", "2.png", "3.png"))
    with pytest.raises(ValueError, match=r"1 of its 3 images left after drop_first=1, max_images=1; .* at least 3"):
        load_diligent(tmp_path / "o", drop_first=1, max_images=1)
    with pytest.raises(ValueError, match=r"2 of its 3 images left after drop_first=1"):
        load_diligent(tmp_path / "o", drop_first=1)
    _handmade_folder(tmp_path / "two", names=("1.png", "2.png"))  # the folder itself is too small: not the options
    with pytest.raises(ValueError, match="light_directions.txt: the 2 light directions span fewer than 3"):
        load_diligent(tmp_path / "two", max_images=5)
    d = load_diligent(tmp_path / "o", drop_first=1, max_images=1, dtype=torch.float64, check_lights=False)
    assert d.names == ["2.png"]
    np.testing.assert_allclose(d.lights.numpy(), ref["lights"][1:2], atol=1e-8)
    np.testing.assert_allclose(d.images[0].numpy(), ref["codes"][1] / 65535.0 / ref["intens"][1], rtol=1e-12)
    with pytest.raises(ValueError, match="no images left"):
        load_diligent(tmp_path / "o", drop_first=3)
    with pytest.raises(ValueError, match="drop_first"):
        load_diligent(tmp_path / "o", drop_first=-1)
    with pytest.raises(TypeError, match="max_images"):
        load_diligent(tmp_path / "o", max_images=1.5)


def test_load_without_filenames_sorts_pngs_and_skips_mask(tmp_path):
    _handmade_folder(tmp_path / "o", names=("002.png", "001.png", "003.png"), write_names=False)
    _write_png(tmp_path / "o" / "normal.png", np.zeros((H, W, 3), np.uint8))
    d = load_diligent(tmp_path / "o")
    assert d.names == ["001.png", "002.png", "003.png"]


def test_load_missing_optional_files_warns(tmp_path):
    _handmade_folder(tmp_path / "o", write_intens=False, write_mask=False)
    with pytest.warns(UserWarning) as rec:
        d = load_diligent(tmp_path / "o")
    msgs = " ".join(str(r.message) for r in rec)
    assert "mask.png" in msgs and "light_intensities" in msgs
    assert bool(d.mask.all())
    assert torch.equal(d.intensities, torch.ones(3, 3))
    (tmp_path / "o" / "Normal_gt.mat").unlink()
    with pytest.warns(UserWarning):
        assert load_diligent(tmp_path / "o").normals_gt is None


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_diligent(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="light_directions.txt"):
        load_diligent(tmp_path / "empty")
    with pytest.raises(TypeError, match="dtype"):
        load_diligent(tmp_path / "empty", dtype=torch.int32)

    def fresh(name, **kw):
        _handmade_folder(tmp_path / name, **kw)
        return tmp_path / name

    p = fresh("count")
    with open(p / "light_directions.txt", "a") as f:
        f.write("0 0 1\n")
    with open(p / "light_intensities.txt", "a") as f:
        f.write("1 1 1\n")
    with pytest.raises(ValueError, match="3 image names .* 4 light directions"):
        load_diligent(p)

    # one file of a good folder replaced: a text file (str or bytes) or a picture
    for i, (name, content, msg) in enumerate([
        ("light_intensities.txt", "1 1 1\n1 1 1\n", "light_intensities.txt has 2 rows"),
        ("light_intensities.txt", "1 1 1\n1 0 1\n1 1 1\n", "row 2.*> 0"),
        ("light_directions.txt", "0 0 1\n0 0 2\n0 0.6 0.8\n", "row 2 has length 2"),
        ("light_directions.txt", "0 0 1\n0 zero 1\n0 0.6 0.8\n", "line 2: malformed"),
        ("light_directions.txt", "0 0 1\n0 1\n0 0.6 0.8\n", "line 2: expected 3 numbers"),
        ("light_directions.txt", b"\x00\x01\xff\xfe" * 8, r"light_directions\.txt: binary file"),
        ("light_directions.txt", b"0 0 1\n\xff\xfe 0 1\n", r"light_directions\.txt: not a UTF-8 text file"),
        ("filenames.txt", "../x.png\nb.png\nc.png\n", "outside the folder"),
        ("filenames.txt", "/etc/x.png\nb.png\nc.png\n", "outside"),
        ("filenames.txt", "a.png\nb.png\na.png\n", "line 3.*repeats line 1"),
        ("filenames.txt", "b.png\n" + "a" * 300 + ".png\nc.png\n", r"filenames\.txt line 2: image name .* not a file"),
        ("a.png", np.zeros((H + 1, W, 3), np.uint16), r"differs from the first image's .* \(b\.png\)"),
        ("a.png", np.zeros((H, W, 3), np.uint8), r"bit depth 8 differs .* \(b\.png\)"),
        ("mask.png", np.zeros((H, W + 2), np.uint8), "mask size"),
    ]):
        p = fresh(f"replaced{i}")
        if isinstance(content, np.ndarray):
            _write_png(p / name, content)
        elif isinstance(content, bytes):
            (p / name).write_bytes(content)
        else:
            (p / name).write_text(content)
        with pytest.raises(ValueError, match=msg):
            load_diligent(p)

    p = fresh("missing")  # the error names the file that lists the missing image
    (p / "a.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"image 'a\.png' \(number 2, listed in filenames\.txt\) not found"):
        load_diligent(p)

    # a grey 16-bit image loads as three equal channels
    p = fresh("grey")
    grey = ((np.arange(H * W).reshape(H, W) * 97) % 65535).astype(np.uint16)
    _write_png(p / "b.png", grey)
    d = load_diligent(p, dtype=torch.float64, normalize_intensities=False)
    for c in range(3):
        np.testing.assert_array_equal(d.images[0, ..., c].numpy(), grey / 65535.0)  # b.png is the first name

    p = fresh("missingimg")
    (p / "c.png").unlink()
    with pytest.raises(FileNotFoundError, match="'c.png'"):
        load_diligent(p)

    p = fresh("normals")
    scipy.io.savemat(str(p / "Normal_gt.mat"), {"Normal_gt": np.zeros((H, W))})
    with pytest.raises(ValueError, match="Normal_gt has shape"):
        load_diligent(p)
    scipy.io.savemat(str(p / "Normal_gt.mat"), {"normals": np.zeros((H, W, 3))})
    with pytest.raises(ValueError, match="no variable 'Normal_gt'"):
        load_diligent(p)

    p = fresh("matcorrupt")
    raw = (p / "Normal_gt.mat").read_bytes()
    (p / "Normal_gt.mat").write_bytes(raw[:200])
    with pytest.raises(ValueError, match=r"Normal_gt\.mat: cannot read the MATLAB file"):
        load_diligent(p)
    (p / "Normal_gt.mat").write_bytes(b"MATLAB 5.0" + bytes(range(256)) * 2)
    with pytest.raises(ValueError, match=r"Normal_gt\.mat"):
        load_diligent(p)

    p = fresh("pngtrunc")
    (p / "a.png").write_bytes((p / "a.png").read_bytes()[:150])
    with pytest.raises(ValueError, match=r"a\.png: cannot decode"):
        load_diligent(p)


@pytest.mark.parametrize("rows,msg", [
    ("0 0.6 0.8\n0 0 1\n0.6 0 -0.8\n", "row 3 has z = -0.8 <= 0"),
    ("0 0.6 0.8\n1 0 0\n0 -0.6 0.8\n", "row 2 has z = 0 <= 0"),
    ("0 0.6 0.8\n0 0.6 0.8\n0 0.6 0.8\n", "fewer than 3 dimensions"),  # identical
    ("0 0.6 0.8\n0 0 1\n0 -0.6 0.8\n", "fewer than 3 dimensions"),  # coplanar with the view (y-z plane)
    ("0.6 0 0.8\n0 0.6 0.8\n0.331295 0.331295 0.883452\n", "fewer than 3 dimensions.*3 non-coplanar lights$"),
])  # fmt: skip
def test_load_rejects_degenerate_lights(tmp_path, rows, msg):
    _handmade_folder(tmp_path / "o")
    (tmp_path / "o" / "light_directions.txt").write_text(rows)
    with pytest.raises(ValueError, match=msg):
        load_diligent(tmp_path / "o")


# --------------------------------------------------------------------------- #
# save_diligent
# --------------------------------------------------------------------------- #
def test_save_load_roundtrip(tmp_path):
    images, lights, intens, mask, normals = _random_scene()
    out = save_diligent(tmp_path / "obj", images, lights, intens, mask, normals)
    assert sorted(p.name for p in out.iterdir()) == [
        "001.png", "002.png", "003.png", "004.png", "005.png", "Normal_gt.mat",
        "filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png",
    ]  # fmt: skip
    assert _png_info(out / "001.png")[2:4] == (16, 2)  # 16-bit RGB on disk
    d = load_diligent(out, dtype=torch.float64)
    scale = 1.0 / float((images * intens[:, None, None, :]).max())
    # stored intensities carry the scale: load gives the radiometrically consistent images back
    _close(d.intensities, intens * scale, rtol=1e-15, atol=0)
    bound = 0.5 / 65535 / (intens * scale)[:, None, None, :] * (1 + 1e-9)
    assert bool(((d.images - images).abs() <= bound).all())
    assert float((d.images - images).abs().max()) > 0  # quantisation really happened
    _close(d.lights, lights, rtol=0, atol=1e-15)
    assert torch.equal(d.mask, mask)
    assert torch.equal(d.normals_gt, normals)
    # float32 load: lights identical to the float32 cast of the originals (up to 1 ulp of renormalisation)
    d32 = load_diligent(out)
    _close(d32.lights, lights.float(), rtol=0, atol=1.2e-7)
    # the brightest recorded value maps to the largest code
    assert int(_read_png(out / f"{int((images * intens[:, None, None]).flatten(1).amax(1).argmax()) + 1:03d}.png").max()) == 65535


def test_save_explicit_scale_and_codes(tmp_path):
    images, lights, intens, _, _ = _random_scene(1)
    out = save_diligent(tmp_path / "o", images, lights, intens, scale=0.1)
    codes = _read_png(out / "002.png")
    expected = np.rint(np.clip((images[1] * intens[1]).numpy() * 0.1, 0, 1) * 65535)
    np.testing.assert_array_equal(codes, expected)
    d = load_diligent(out, dtype=torch.float64)
    _close(d.intensities, intens * 0.1)
    assert torch.equal(d.mask, torch.ones(H, W, dtype=torch.bool))  # default mask: all valid
    assert d.normals_gt is None


def test_save_clips_with_warning(tmp_path):
    images, lights, _, _, _ = _random_scene(2)
    images[0, 0, 0] = -0.5
    with pytest.warns(UserWarning, match="exceed"):
        with pytest.warns(UserWarning, match="negative"):
            save_diligent(tmp_path / "o", images, lights, scale=1.0)
    d = load_diligent(tmp_path / "o")
    assert float(d.images.max()) == 1.0 and float(d.images.min()) == 0.0


def test_save_all_black_images(tmp_path):
    images, lights, _, _, _ = _random_scene()
    save_diligent(tmp_path / "o", torch.zeros_like(images), lights)
    assert (load_diligent(tmp_path / "o").images == 0).all()


def test_png_writer_rejects_bad_shapes(tmp_path):
    for shape in [(4, 4, 2), (4, 4, 5), (4,)]:
        with pytest.raises(ValueError, match="PNG data must have shape"):
            _write_png(tmp_path / "x.png", np.zeros(shape, np.uint8))


def test_save_8bit(tmp_path):
    images, lights, intens, _, _ = _random_scene(3)
    save_diligent(tmp_path / "o", images, lights, intens, bit_depth=8)
    assert _png_info(tmp_path / "o" / "001.png")[2] == 8
    with pytest.warns(UserWarning, match="8-bit"):
        d = load_diligent(tmp_path / "o", dtype=torch.float64)
    bound = 0.5 / 255 / d.intensities[:, None, None, :] * (1 + 1e-9)
    assert bool(((d.images - images).abs() <= bound).all())


def test_save_refuses_non_empty_folder(tmp_path):
    images, lights, _, _, _ = _random_scene()
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_diligent(tmp_path / "o", images, lights)
    save_diligent(tmp_path / "o", images, lights, overwrite=True)
    assert (tmp_path / "o" / "keep.txt").exists()
    _close(load_diligent(tmp_path / "o", dtype=torch.float64).lights, lights, rtol=0, atol=1e-15)
    # only its own files are replaced: an unrelated Normal_gt.mat is neither deleted nor left as ground truth
    scipy.io.savemat(str(tmp_path / "o" / "Normal_gt.mat"), {"Normal_gt": np.ones((H, W, 3))})
    before = (tmp_path / "o" / "Normal_gt.mat").read_bytes()
    with pytest.raises(FileExistsError, match="Normal_gt.mat"):
        save_diligent(tmp_path / "o", images, lights, overwrite=True)
    assert (tmp_path / "o" / "Normal_gt.mat").read_bytes() == before
    normals = torch.nn.functional.normalize(torch.rand(H, W, 3, dtype=torch.float64) + 0.1, dim=-1)
    save_diligent(tmp_path / "o", images, lights, normals_gt=normals, overwrite=True)
    assert torch.equal(load_diligent(tmp_path / "o", dtype=torch.float64).normals_gt, normals)
    # an empty existing folder is fine without overwrite
    (tmp_path / "e").mkdir()
    save_diligent(tmp_path / "e", images, lights)


def test_save_custom_names(tmp_path):
    images, lights, _, _, _ = _random_scene()
    names = [f"img_{i}.png" for i in range(L)][::-1]
    save_diligent(tmp_path / "o", images, lights, names=names)
    assert load_diligent(tmp_path / "o").names == names
    with pytest.raises(ValueError, match="distinct"):
        save_diligent(tmp_path / "p", images, lights, names=["a.png"] * L)
    with pytest.raises(ValueError, match="mask"):
        save_diligent(tmp_path / "p", images, lights, names=["mask.png"] + names[1:])


def test_save_argument_errors(tmp_path):
    images, lights, intens, mask, normals = _random_scene()
    p = tmp_path / "o"
    with pytest.raises(ValueError, match=r"images.*\(L, H, W, 3\)"):
        save_diligent(p, images[..., :2], lights)
    with pytest.raises(ValueError, match="lights"):
        save_diligent(p, images, lights[:2])
    with pytest.raises(ValueError, match="zero vector"):
        save_diligent(p, images, torch.zeros(L, 3))
    with pytest.raises(ValueError, match="intensities"):
        save_diligent(p, images, lights, -intens)
    with pytest.raises(ValueError, match="mask"):
        save_diligent(p, images, lights, mask=mask[:2])
    with pytest.raises(ValueError, match="normals_gt"):
        save_diligent(p, images, lights, normals_gt=normals[..., :2])
    with pytest.raises(ValueError, match="normals_gt"):  # H and W must be the images'
        save_diligent(p, images, lights, normals_gt=normals[1:])
    with pytest.raises(ValueError, match="bit_depth"):
        save_diligent(p, images, lights, bit_depth=12)
    with pytest.raises(ValueError, match="scale"):
        save_diligent(p, images, lights, scale=-1.0)
    bad = images.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        save_diligent(p, bad, lights)
    with pytest.raises(TypeError, match="images"):
        save_diligent(p, images.tolist(), lights)
    assert not p.exists()  # nothing written on argument errors


def test_dataset_to():
    d = PhotometricDataset(
        images=torch.zeros(1, 2, 2, 3), lights=torch.tensor([[0.0, 0.0, 1.0]]), intensities=torch.ones(1, 3),
        mask=torch.ones(2, 2, dtype=torch.bool), normals_gt=None, names=["a.png"], path=None,
    )  # fmt: skip
    e = d.to(dtype=torch.float64)
    assert e.images.dtype == torch.float64 and e.mask.dtype == torch.bool and e.normals_gt is None


def test_corrupt_normal_gt_that_crashes_scipy_gives_an_error_naming_the_file(tmp_path, monkeypatch):
    """One changed byte in a MAT file can make scipy's loadmat segfault: the file is read in a child process."""
    from torch_hsh.io import diligent as D

    _handmade_folder(tmp_path / "o")
    f = tmp_path / "o" / "Normal_gt.mat"
    raw = bytearray(f.read_bytes())
    raw[180] = 0xFF  # inside the array's data element: segfaulted scipy 1.x's reader (exit 139, no message)
    f.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"Normal_gt\.mat: (the MATLAB file is corrupt|cannot read)"):
        load_diligent(tmp_path / "o")
    # whatever this scipy does with that byte: a reader that crashes is reported, with the file named
    monkeypatch.setattr(D, "_MAT_READER", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)")
    with pytest.raises(ValueError, match=r"Normal_gt\.mat: the MATLAB file is corrupt: scipy's reader crashed "
                                         r"on it \(SIGSEGV\)"):
        load_diligent(tmp_path / "o")


@pytest.mark.parametrize("bad", ["nan", "inf", "long", "zero", "inf_outside"])
def test_normal_gt_must_hold_finite_unit_normals_inside_the_mask(tmp_path, bad):
    info = _handmade_folder(tmp_path / "o")
    n = info["normals"].copy()
    i, j = np.argwhere(info["mask"])[0]
    n[~info["mask"]] = 0.0  # outside the mask DiLiGenT stores zeros: not unit, but fine
    if bad == "inf_outside":
        i, j = np.argwhere(~info["mask"])[0]
    n[i, j] = {"nan": [np.nan, 0, 1], "inf": [0, np.inf, 1], "long": [0, 0, 1.5], "zero": [0, 0, 0],
               "inf_outside": [np.inf, 0, 0]}[bad]
    scipy.io.savemat(str(tmp_path / "o" / "Normal_gt.mat"), {"Normal_gt": n})
    msg = {"nan": r"NaN or Inf values at 1 pixels \(1 inside", "inf": r"NaN or Inf values at 1 pixels \(1 inside",
           "inf_outside": r"NaN or Inf values at 1 pixels \(0 inside"}.get(bad, "not a unit normal at 1 of the")
    with pytest.raises(ValueError, match=msg) as ei:
        load_diligent(tmp_path / "o")
    assert str(tmp_path / "o" / "Normal_gt.mat") in str(ei.value)
    n[i, j] = [0.0, 0.6, 0.8]
    scipy.io.savemat(str(tmp_path / "o" / "Normal_gt.mat"), {"Normal_gt": n})
    assert load_diligent(tmp_path / "o").normals_gt is not None
