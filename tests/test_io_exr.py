"""Tests for torch_hsh.io.exr (OpenEXR read / write helpers)."""
import numpy as np
import OpenEXR
import pytest
import torch

from torch_hsh.io.exr import (
    read_coefficient_maps_exr,
    read_envmap,
    read_exr,
    read_image_stack_exr,
    write_coefficient_maps_exr,
    write_exr,
    write_image_stack_exr,
    write_normal_map_exr,
)

H, W = 5, 7


def _rand(*shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape).astype(np.float32)


def test_write_read_roundtrip_float32_exact(tmp_path):
    z = _rand(H, W)
    rgb = torch.from_numpy(_rand(H, W, 3, seed=1))
    f = write_exr(tmp_path / "a.exr", {"Z": z, "col": rgb, "": _rand(H, W, 3, seed=2), "many": _rand(H, W, 11, seed=3)})
    ch = read_exr(f)
    assert set(ch) == {"Z", "col.R", "col.G", "col.B", "R", "G", "B"} | {f"many.{k:02d}" for k in range(11)}
    assert all(a.dtype == np.float32 and a.shape == (H, W) for a in ch.values())
    np.testing.assert_array_equal(ch["Z"], z)
    np.testing.assert_array_equal(np.stack([ch["col.R"], ch["col.G"], ch["col.B"]], -1), rgb.numpy())
    np.testing.assert_array_equal(ch["many.10"], _rand(H, W, 11, seed=3)[..., 10])


def test_input_dict_not_mutated_and_float64_and_noncontiguous(tmp_path):
    base = np.random.default_rng(4).random((H, 2 * W))
    src = {"X": base[:, ::2]}  # float64, non-contiguous view
    write_exr(tmp_path / "b.exr", src)
    assert isinstance(src["X"], np.ndarray)  # OpenEXR.File replaces dict values: we must not pass the user's dict
    np.testing.assert_array_equal(read_exr(tmp_path / "b.exr")["X"], base[:, ::2].astype(np.float32))


def test_half_storage(tmp_path):
    z = _rand(H, W) * 100
    write_exr(tmp_path / "h.exr", {"Z": z}, half=True)
    with OpenEXR.File(str(tmp_path / "h.exr"), separate_channels=True) as f:
        assert f.channels()["Z"].pixels.dtype == np.float16
    got = read_exr(tmp_path / "h.exr")["Z"]
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, z.astype(np.float16).astype(np.float32))
    assert not np.array_equal(got, z)  # really stored in half precision


def test_write_exr_errors(tmp_path):
    write_exr(tmp_path / "a.exr", {"Z": np.zeros((H, W))})
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_exr(tmp_path / "a.exr", {"Z": np.ones((H, W))})
    write_exr(tmp_path / "a.exr", {"Z": np.ones((H, W))}, overwrite=True)
    assert read_exr(tmp_path / "a.exr")["Z"].min() == 1.0
    with pytest.raises(ValueError, match="size"):
        write_exr(tmp_path / "c.exr", {"A": np.zeros((H, W)), "B": np.zeros((H, W + 1))})
    with pytest.raises(ValueError, match=r"\(H, W\) or \(H, W, C\)"):
        write_exr(tmp_path / "c.exr", {"A": np.zeros(5)})
    with pytest.raises(ValueError, match="channel name"):
        write_exr(tmp_path / "c.exr", {"a b": np.zeros((H, W))})
    with pytest.raises(ValueError, match="duplicate"):
        write_exr(tmp_path / "c.exr", {"c.R": np.zeros((H, W)), "c": np.zeros((H, W, 3))})
    with pytest.raises(TypeError, match="non-empty dict"):
        write_exr(tmp_path / "c.exr", {})
    with pytest.raises(TypeError, match="numpy array or torch.Tensor"):
        write_exr(tmp_path / "c.exr", {"A": [[0.0]]})
    with pytest.raises(TypeError, match="header attribute"):
        write_exr(tmp_path / "c.exr", {"A": np.zeros((H, W))}, header={"k": [1]})
    assert not (tmp_path / "c.exr").exists()


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "fake.exr").write_bytes(b"\x89PNG\r\n\x1a\nnot an exr")
    with pytest.raises(ValueError, match="not an OpenEXR file"):
        read_exr(tmp_path / "fake.exr")
    with pytest.raises(ValueError, match="not an OpenEXR file"):
        read_envmap(tmp_path / "fake.exr")
    with pytest.raises(FileNotFoundError):
        read_coefficient_maps_exr(tmp_path / "missing.exr")
    # correct magic, truncated body
    (tmp_path / "trunc.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\x00" * 10)
    with pytest.raises(ValueError, match="could not read"):
        read_exr(tmp_path / "trunc.exr")


def test_truncated_pixel_data_names_the_file(tmp_path):
    write_exr(tmp_path / "full.exr", {"R": np.random.default_rng(0).random((64, 64)).astype(np.float32)})
    raw = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "half.exr").write_bytes(raw[: len(raw) // 2])  # header intact, pixel chunks cut
    for reader in (read_exr, read_envmap, read_image_stack_exr):
        # the message names the file (the reason's wording depends on the OpenEXR version)
        with pytest.raises(ValueError, match=r"could not read OpenEXR file .*half\.exr: "):
            reader(tmp_path / "half.exr")
    cm = tmp_path / "cm.exr"
    write_coefficient_maps_exr(cm, np.random.default_rng(1).random((64, 64, 3, 4)).astype(np.float32))
    raw = cm.read_bytes()
    cm.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"could not read OpenEXR file .*cm\.exr: "):
        read_coefficient_maps_exr(cm)


def test_data_window_larger_than_the_file_is_refused_before_the_pixels_are_read(tmp_path, monkeypatch):
    import struct

    import torch_hsh.io.exr as exr

    f = write_exr(tmp_path / "big.exr", {"": _rand(4, 8, 3)})
    d = bytearray(f.read_bytes())
    k = d.find(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    d[k + 8:k + 12] = struct.pack("<i", 20_000_000)  # xMax: 20 million x 4 rows x 3 channels in a 400-byte file
    f.write_bytes(bytes(d))
    opened = []

    class Recording:
        def File(self, path, **kwargs):
            opened.append(kwargs)
            return OpenEXR.File(path, **kwargs)

    monkeypatch.setattr(exr, "_openexr", Recording)
    with pytest.raises(ValueError, match=r"big\.exr: the OpenEXR header claims 960000048 decoded bytes"):
        read_exr(f)
    assert opened == [{"header_only": True}]  # the bindings never allocated the claimed pixels


def test_stack_of_mixed_images_and_a_binary_header_attribute_name_the_file(tmp_path):
    write_exr(tmp_path / "mixed.exr", {"img000": _rand(H, W), "img001": _rand(H, W, 3)})
    with pytest.raises(ValueError, match=r"mixed\.exr: the images of the stack differ"):  # was numpy's np.stack error
        read_image_stack_exr(tmp_path / "mixed.exr")
    f = tmp_path / "attr.exr"
    write_coefficient_maps_exr(f, _rand(H, W, 3, 4))
    d = bytearray(f.read_bytes())
    k = d.find(b"torch_hsh_colors\x00string\x00") + len(b"torch_hsh_colors\x00")
    d[k + 4:k + 6] = b"\xff\xf0"  # the attribute's type name is no longer UTF-8: UnicodeDecodeError on access
    f.write_bytes(bytes(d))
    # the lowest OpenEXR fails at open, a newer one on access: both must name the file
    with pytest.raises(ValueError, match=r"attr\.exr: "):
        read_coefficient_maps_exr(f)


def test_image_stack_roundtrip(tmp_path):
    imgs = torch.rand(12, H, W, 3, dtype=torch.float64)
    write_image_stack_exr(tmp_path / "s.exr", imgs)
    back = read_image_stack_exr(tmp_path / "s.exr")
    assert back.shape == (12, H, W, 3)
    np.testing.assert_array_equal(back, imgs.float().numpy())  # image order survives alphabetical sorting
    gray = torch.rand(3, H, W)
    write_image_stack_exr(tmp_path / "g.exr", gray)
    np.testing.assert_array_equal(read_image_stack_exr(tmp_path / "g.exr"), gray.numpy())
    with pytest.raises(ValueError, match="images"):
        write_image_stack_exr(tmp_path / "x.exr", torch.rand(H, W))
    write_exr(tmp_path / "other.exr", {"Z": np.zeros((H, W))})
    with pytest.raises(ValueError, match="image stack"):
        read_image_stack_exr(tmp_path / "other.exr")


def test_normal_map(tmp_path):
    n = torch.nn.functional.normalize(torch.randn(H, W, 3), dim=-1)
    mask = torch.rand(H, W) > 0.5
    write_normal_map_exr(tmp_path / "n.exr", n, mask)
    ch = read_exr(tmp_path / "n.exr")
    got = np.stack([ch["normal.X"], ch["normal.Y"], ch["normal.Z"]], -1)
    np.testing.assert_array_equal(got, np.where(mask.numpy()[..., None], n.numpy(), 0))
    np.testing.assert_array_equal(ch["mask"], mask.numpy().astype(np.float32))
    write_normal_map_exr(tmp_path / "n2.exr", n)
    assert set(read_exr(tmp_path / "n2.exr")) == {"normal.X", "normal.Y", "normal.Z"}
    with pytest.raises(ValueError, match="normals"):
        write_normal_map_exr(tmp_path / "n3.exr", n[..., :2])
    with pytest.raises(ValueError, match="mask"):
        write_normal_map_exr(tmp_path / "n3.exr", n, mask[:2])


def test_coefficient_maps_roundtrip_exact(tmp_path):
    k = 12
    coefficients = torch.randn(H, W, 3, k, dtype=torch.float64) * 1e3
    names = [f"a_{p}_{r}_{q}" for p, r, q in [(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1)]] + [f"z{i}" for i in range(8)]
    names = names[::-1]  # not alphabetical: order must come from the header
    write_coefficient_maps_exr(tmp_path / "c.exr", coefficients, names=names)
    ch = read_exr(tmp_path / "c.exr")
    assert "R.a_1_1_0" in ch and "B.z7" in ch and len(ch) == 3 * k
    back, got_names, colors = read_coefficient_maps_exr(tmp_path / "c.exr")
    assert got_names == names and colors == ["R", "G", "B"]
    assert back.dtype == np.float32 and back.shape == (H, W, 3, k)
    np.testing.assert_array_equal(back, coefficients.float().numpy())
    np.testing.assert_array_equal(ch["G.a_1_0_0"], coefficients[:, :, 1, names.index("a_1_0_0")].float().numpy())
    # default names, single channel from (H, W, K)
    mono = np.random.default_rng(0).random((H, W, 4)).astype(np.float32)
    write_coefficient_maps_exr(tmp_path / "m.exr", mono)
    back, got_names, colors = read_coefficient_maps_exr(tmp_path / "m.exr")
    assert got_names == ["c0000", "c0001", "c0002", "c0003"] and colors == ["Y"]
    np.testing.assert_array_equal(back[:, :, 0], mono)


def test_coefficient_maps_errors(tmp_path):
    c = np.zeros((H, W, 3, 2), np.float32)
    with pytest.raises(ValueError, match="names"):
        write_coefficient_maps_exr(tmp_path / "c.exr", c, names=["a"])
    with pytest.raises(ValueError, match="names"):
        write_coefficient_maps_exr(tmp_path / "c.exr", c, names=["a", "a"])
    with pytest.raises(ValueError, match="invalid"):
        write_coefficient_maps_exr(tmp_path / "c.exr", c, names=["a.b", "c"])
    with pytest.raises(ValueError, match="colors"):
        write_coefficient_maps_exr(tmp_path / "c.exr", c, colors=["R", "G"])
    with pytest.raises(ValueError, match=r"\(H, W, C, K\)"):
        write_coefficient_maps_exr(tmp_path / "c.exr", np.zeros((H, W)))
    write_exr(tmp_path / "plain.exr", {"R": np.zeros((H, W))})
    with pytest.raises(ValueError, match="not a coefficient-map EXR"):
        read_coefficient_maps_exr(tmp_path / "plain.exr")


def test_read_envmap_layouts(tmp_path):
    env = np.abs(_rand(4, 8, 3)) * 50
    # what the shared envmaps look like: half-float bare R, G, B channels written as one "RGB" array
    with OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": env.astype(np.float16)}) as f:  # fmt: skip
        f.write(str(tmp_path / "e.exr"))
    got = read_envmap(tmp_path / "e.exr")
    assert got.shape == (4, 8, 3) and got.dtype == np.float32
    np.testing.assert_array_equal(got, env.astype(np.float16).astype(np.float32))
    write_exr(tmp_path / "layer.exr", {"sky": env})
    np.testing.assert_array_equal(read_envmap(tmp_path / "layer.exr"), env)
    write_exr(tmp_path / "y.exr", {"Y": env[..., 0]})
    np.testing.assert_array_equal(read_envmap(tmp_path / "y.exr"), np.repeat(env[..., :1], 3, -1))
    write_exr(tmp_path / "two.exr", {"a": env, "b": env})
    with pytest.raises(ValueError, match="no unique R, G, B"):
        read_envmap(tmp_path / "two.exr")
