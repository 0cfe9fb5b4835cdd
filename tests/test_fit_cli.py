"""``torch-hsh fit`` (issue 23): a specular MERL table is fitted on its samples, the error is reported and
stored, ``--out`` is checked before any work, and every option an error message names exists."""
import json
import re

import numpy as np
import pytest
import torch

from torch_hsh import cli
from torch_hsh.cli import fit as fit_cli
from torch_hsh.brdf import CookTorranceGGX, Lambertian
from torch_hsh.io import merl
from torch_hsh.io.merl import fit_merl, tabulate_merl, write_merl


def _run(argv, capsys):
    try:
        code = cli.main(argv)
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def ggx_file(tmp_path_factory):
    t = tabulate_merl(CookTorranceGGX(albedo=0.5, specular=0.5, roughness=0.3), shape=(20, 20, 40))
    return write_merl(tmp_path_factory.mktemp("merl") / "ggx.binary", t)


@pytest.fixture
def no_fit(monkeypatch):
    """Fail loudly if the computation starts (for checks that must come before it)."""

    def boom(*a, **k):
        raise AssertionError("the fit ran before the argument checks")

    monkeypatch.setattr(merl, "fit_merl", boom)


def test_fit_specular_table_reports_and_stores_the_error(tmp_path, capsys, ggx_file):
    out = tmp_path / "sub" / "dir" / "g.npz"  # missing parents are created at the end
    code, stdout, stderr = _run(["fit", str(ggx_file), "--order", "4", "--out", str(out)], capsys)
    assert code == 0, stderr
    z = np.load(out)
    a, info = fit_merl(ggx_file, 4, return_info=True)
    np.testing.assert_allclose(z["coefficients"], a.numpy(), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(z["relative_error"], info["relative_error"].numpy(), rtol=1e-12)
    np.testing.assert_allclose(z["energy_accuracy"], info["accuracy"].numpy(), rtol=1e-12)
    meta = json.loads(str(z["metadata"]))
    assert meta["method"] == "samples" and meta["order"] == 4
    assert meta["relative_error"] == pytest.approx(info["relative_error"].tolist())
    # printed (stdout) with the number, progress on stderr
    shown = re.search(r"relative L2 error on the table's samples \(R, G, B\): ([0-9.e-]+)", stdout)
    assert shown and float(shown.group(1)) == pytest.approx(float(info["relative_error"][0]), rel=1e-3)
    assert "fit_merl P=4" in stderr and "fit_merl" not in stdout
    # --quiet: nothing at all, not even the bar
    code, stdout, stderr = _run(["fit", str(ggx_file), "--order", "1", "--out", str(out), "--overwrite", "--quiet"],
                                capsys)
    assert code == 0 and stdout == "" and stderr == ""


def test_ridge_and_cutoff_reach_the_fit(tmp_path, capsys, ggx_file, monkeypatch):
    seen = {}
    real = merl.fit_merl

    def spy(brdf, order, **kw):
        seen.update(kw)
        return real(brdf, order, **kw)

    monkeypatch.setattr(merl, "fit_merl", spy)
    code, _, err = _run(["fit", str(ggx_file), "--order", "2", "--out", str(tmp_path / "a.npz"), "--quiet",
                         "--ridge", "1e-3", "--grazing-cutoff", "0.1"], capsys)
    assert code == 0, err
    assert seen["ridge"] == 1e-3 and seen["grazing_cutoff"] == 0.1
    meta = json.loads(str(np.load(tmp_path / "a.npz")["metadata"]))
    assert meta["ridge"] == 1e-3 and meta["grazing_cutoff"] == 0.1


@pytest.mark.parametrize("extra, msg", [
    (["--ridge", "-1"], "--ridge"),
    (["--grazing-cutoff", "1"], "--grazing-cutoff"),
    (["--tol", "0.01"], "--tol: applies to --method quadrature only"),
    (["--method", "quadrature", "--ridge", "0.1"], "--ridge: applies to --method samples only"),
    (["--method", "quadrature", "--tol", "2"], "--tol"),
])
def test_bad_options_exit_2_before_the_fit(tmp_path, capsys, ggx_file, no_fit, extra, msg):
    code, _, err = _run(["fit", str(ggx_file), "--out", str(tmp_path / "a.npz"), "--quiet"] + extra, capsys)
    assert code == 2
    assert msg in err.strip().splitlines()[-1]  # in the error line, not only in the usage block


def test_out_is_checked_before_the_fit(tmp_path, capsys, ggx_file, no_fit, monkeypatch):
    existing = tmp_path / "old.npz"
    existing.write_bytes(b"user data")
    code, _, err = _run(["fit", str(ggx_file), "--out", str(existing), "--quiet"], capsys)
    assert code == 2 and "exists; pass --overwrite" in err.splitlines()[-1]
    assert existing.read_bytes() == b"user data"
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = _run(["fit", str(ggx_file), "--out", str(blocker / "a.npz"), "--quiet"], capsys)
    assert code == 2 and "is not a folder" in err.splitlines()[-1]
    code, _, err = _run(["fit", str(ggx_file), "--out", str(tmp_path / "a.txt"), "--quiet"], capsys)
    assert code == 2 and ".npz" in err.splitlines()[-1]

    # a folder that os.access calls writable but where no file can be created (root and /proc): the probe
    def refuse(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(fit_cli.tempfile, "mkstemp", refuse)
    code, _, err = _run(["fit", str(ggx_file), "--out", str(tmp_path / "new" / "a.npz"), "--quiet"], capsys)
    assert code == 2 and "cannot write into" in err.splitlines()[-1]
    assert not (tmp_path / "new").exists()


def test_failed_fit_leaves_no_folders(tmp_path, capsys, ggx_file, monkeypatch):
    def fail(*a, **k):
        raise ValueError("boom")

    monkeypatch.setattr(merl, "fit_merl", fail)
    out = tmp_path / "x" / "y" / "a.npz"
    code, _, err = _run(["fit", str(ggx_file), "--out", str(out), "--quiet"], capsys)
    assert code == 1 and "boom" in err
    assert not (tmp_path / "x").exists()


def _fit_options():
    ap = cli.build_parser()
    sub = next(a for a in ap._actions if a.dest == "command")
    return {s for a in sub.choices["fit"]._actions for s in a.option_strings}


def test_error_messages_name_only_options_that_exist(tmp_path, capsys, ggx_file):
    opts = _fit_options()
    # the quadrature path runs out of budget on a specular table: the message must be followable on the CLI
    code, _, err = _run(["fit", str(ggx_file), "--order", "2", "--out", str(tmp_path / "a.npz"), "--quiet",
                         "--method", "quadrature", "--max-evaluations", "100000"], capsys)
    assert code == 1
    line = err.strip().splitlines()[-1]
    named = set(re.findall(r"--[a-z][a-z-]*", line))
    assert {"--max-evaluations", "--accept-unconverged", "--grazing-cutoff", "--method"} <= named, line
    assert named <= opts, named - opts
    assert "strict=False" not in line and "grazing_cutoff" not in line
    # following it works: --accept-unconverged writes the best result
    code, _, err = _run(["fit", str(ggx_file), "--order", "2", "--out", str(tmp_path / "a.npz"), "--quiet",
                         "--method", "quadrature", "--max-evaluations", "100000", "--accept-unconverged",
                         "--grazing-cutoff", "0.05"], capsys)
    assert code == 0, err
    warned = [ln for ln in err.splitlines() if "warning:" in ln]
    assert len(warned) == 2 and all("did not converge" in ln and "strict=False" not in ln for ln in warned)
    # the samples path: too few samples for the order -> --ridge
    small = write_merl(tmp_path / "tiny.binary", tabulate_merl(Lambertian(0.5), shape=(2, 2, 2)))
    code, _, err = _run(["fit", str(small), "--order", "4", "--out", str(tmp_path / "b.npz"), "--quiet"], capsys)
    assert code == 1
    line = err.strip().splitlines()[-1]
    named = set(re.findall(r"--[a-z][a-z-]*", line))
    assert "--ridge" in named and named <= opts
    code, _, err = _run(["fit", str(small), "--order", "4", "--out", str(tmp_path / "b.npz"), "--quiet",
                         "--ridge", "1e-6"], capsys)
    assert code == 0, err


def test_lambertian_table_is_exact_on_the_cli(tmp_path, capsys):
    f = write_merl(tmp_path / "l.binary", tabulate_merl(Lambertian(0.5), shape=(8, 8, 16)))
    code, _, err = _run(["fit", str(f), "--order", "3", "--out", str(tmp_path / "l.npz"), "--quiet"], capsys)
    assert code == 0, err
    z = np.load(tmp_path / "l.npz")
    assert abs(z["coefficients"][0, 0] - 1.0) < 1e-12 and float(z["relative_error"].max()) < 1e-6
    assert torch.tensor(z["energy_accuracy"]).min() > 1 - 1e-12


def test_fit_out_defaults_to_the_table_name_beside_it(tmp_path, capsys, ggx_file):
    src = tmp_path / "my_material.binary"
    src.write_bytes(ggx_file.read_bytes())
    code, _, stderr = _run(["fit", str(src), "--order", "1", "--quiet"], capsys)
    assert code == 0, stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["my_material.binary", "my_material.npz"]
    code, _, stderr = _run(["fit", str(src), "--order", "1", "--quiet"], capsys)  # refused the second time
    assert code == 2 and "my_material.npz exists" in stderr
