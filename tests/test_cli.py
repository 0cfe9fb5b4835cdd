"""Tests for the ``torch-hsh`` command (torch_hsh.cli): exit codes, validation before any folder is
created, refusal of folders that are not ours, atomic replacement, strict JSON, confidence output.

The folder mechanics are tested with a fast stand-in for ``ps.solve_hsh`` (Lambertian normals and
a constant coefficient map); the real solver runs end to end in tests/test_example_ps.py.
"""
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import torch_hsh
from torch_hsh import cli, ps
from torch_hsh.cli import result_folder
from torch_hsh.ps import cli as ps_cli
from torch_hsh.render.scenes import synthetic_scene
from torch_hsh.io.diligent import _read_png, save_diligent

ROOT = Path(__file__).resolve().parents[1]
try:
    import matplotlib  # noqa: F401  (error_map.png / relighting.png need it; the rest does not)

    FIGURES = ("error_map.png", "relighting.png")
except ImportError:  # pragma: no cover - the lowest-versions check installs it, a bare install may not
    FIGURES = ()
FAST = ["--scene", "small", "--size", "12", "--lights", "8", "--quiet"]


def _strict_json(path):
    def no_constants(name):
        raise AssertionError(f"{path} holds the non-JSON constant {name}")

    return json.loads(Path(path).read_text(), parse_constant=no_constants)


@pytest.fixture
def fake_solver(monkeypatch):
    """Replace solve_hsh by Lambertian normals + a constant coefficient map; returns the call log."""
    calls = []
    state = {"confidence": None, "fail_in_pictures": None}

    def solve(images, lights, intensities=None, mask=None, order=3, materials=None, progress=False, **kw):
        calls.append(dict(order=order, materials=materials, lights=int(lights.shape[0]), **kw))
        lam = ps.lambertian_ls(images, lights, intensities, mask)
        K = torch_hsh.num_isotropic(order)
        coefficients = torch.zeros(*mask.shape, 3, K, dtype=images.dtype)
        coefficients[..., 0] = 1.0
        conf = state["confidence"]
        return SimpleNamespace(
            normals=lam.normals, coefficients=coefficients, info={"noise_sigma": float("nan"), "iterations": 3},
            relight=lambda l, e=None: torch.zeros(l.shape[0], *mask.shape, 3, dtype=images.dtype),
            confidence=None if conf is None else conf(mask),
        )

    monkeypatch.setattr(ps, "solve_hsh", solve)
    real_pictures = ps_cli._save_pictures

    def pictures(*a, **k):
        if state["fail_in_pictures"] is not None:
            raise state["fail_in_pictures"]
        return real_pictures(*a, **k)

    monkeypatch.setattr(ps_cli, "_save_pictures", pictures)
    return SimpleNamespace(calls=calls, state=state)


def _run(argv, capsys=None):
    """(exit status, stderr) of an in-process ``torch-hsh`` run."""
    try:
        cli.main(argv)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    err = capsys.readouterr().err if capsys is not None else ""
    return code, err


def _error_line(err):
    """The message of an argparse-style error: the ``prog: error: ...`` line, without the usage block
    (which names every option, so a match on the whole of stderr would pass for any error)."""
    lines = [ln for ln in err.strip().splitlines() if ": error: " in ln]
    assert lines, err
    return lines[-1].split(": error: ", 1)[1]


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir())}


def _leftovers(parent):
    return [p.name for p in Path(parent).iterdir() if p.name.startswith(".")]


# --------------------------------------------------------------------------- #
# arguments: exit 2, nothing created
# --------------------------------------------------------------------------- #
def test_help_lists_the_options(capsys):
    code, _ = _run(["ps", "--help"])
    out = capsys.readouterr().out
    assert code == 0
    for opt in ("CAPTURE", "--linear-input", "--out", "--holdout", "--drop-first", "--max-images", "--threads",
                "--device", "--quiet", "--debug", "--overwrite"):
        assert opt in out, opt
    assert "--scene" not in out and "--data" not in out  # the synthetic scenes are `torch-hsh demo`'s
    code, _ = _run(["demo", "--help"])
    out = capsys.readouterr().out
    assert code == 0 and "--scene" in out and "--linear-input" not in out


@pytest.mark.parametrize("extra,msg", [
    (["--holdout", "-3"], "--holdout"),
    (["--holdout", "6"], "between 1 and L-3 = 5"),  # 8 lights
    (["--order", "x"], "--order"),
    (["--max-images", "3"], "--max-images: must be >= 4"),
    (["--drop-first", "7"], "--drop-first"),  # 1 image left of 8
    (["--drop-first", "5"], "--drop-first/--max-images: 3 synthetic image(s) left; at least 4"),
    (["--device", "nonsense"], "--device"),
    (["--threads", "0"], "--threads"),
    (["--materials", "99"], "--materials: expected 'auto' or an integer between 0 (independent BRDFs) and 8"),
    (["--materials", "foo"], "--materials: expected 'auto'"),
])  # fmt: skip
def test_bad_arguments_exit_2_before_any_folder(tmp_path, capsys, fake_solver, extra, msg):
    out = tmp_path / "res"
    code, err = _run(["demo", "--out", str(out), *FAST, *extra], capsys)
    assert code == 2 and msg in _error_line(err), err
    assert not out.exists() and os.listdir(tmp_path) == []
    assert fake_solver.calls == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message when CUDA is missing")
def test_device_cuda_without_cuda(tmp_path, capsys, fake_solver):
    code, err = _run(["demo", "--out", str(tmp_path / "r"), *FAST, "--device", "cuda"], capsys)
    assert code == 2 and "CUDA is not available" in err
    assert os.listdir(tmp_path) == []


def test_unwritable_out_fails_before_the_solve(tmp_path, capsys, fake_solver):
    (tmp_path / "file.txt").write_text("x")
    code, err = _run(["demo", "--out", str(tmp_path / "file.txt" / "res"), *FAST], capsys)
    assert code == 2 and "is not a folder" in err
    code, err = _run(["demo", "--out", str(tmp_path / "file.txt"), *FAST], capsys)
    assert code == 2 and "not a folder" in err
    assert fake_solver.calls == [] and sorted(os.listdir(tmp_path)) == ["file.txt"]


def test_unwritable_parent_detected(tmp_path, capsys, fake_solver, monkeypatch):
    # root may write anywhere, so the permission answer is simulated
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != tmp_path)
    code, err = _run(["demo", "--out", str(tmp_path / "a" / "b"), *FAST], capsys)
    assert code == 2 and "is not writable" in err
    assert fake_solver.calls == [] and os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- #
# input files: exit 1, one line naming the file
# --------------------------------------------------------------------------- #
def _small_dataset(folder, normals=False):
    scene = synthetic_scene(12, 8)
    save_diligent(folder, scene["images"], scene["lights"], scene["intensities"], scene["mask"],
                  scene["normals_gt"] if normals else None)
    return folder


def test_bad_input_file_one_line_exit_1(tmp_path, capsys, fake_solver):
    data = _small_dataset(tmp_path / "obj")
    (data / "light_directions.txt").write_bytes(bytes(range(256)))
    out = tmp_path / "res"
    code, err = _run(["ps", str(data), "--out", str(out), "--quiet"], capsys)
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "light_directions.txt" in lines[0] and "Traceback" not in err
    assert not out.exists() and fake_solver.calls == []
    code, err = _run(["ps", str(data), "--out", str(out), "--quiet", "--debug"], capsys)
    assert code == 1 and "Traceback" in err and "light_directions.txt" in err


@pytest.mark.parametrize("extra,msg", [
    (["--scene", "small"], "unrecognized arguments: --scene"),  # the synthetic scenes are `torch-hsh demo`'s
    (["--drop-first", "6"], "argument --drop-first/--max-images: "),  # 2 of 8 images left
    (["--linear-input"], "argument --linear-input: applies to RTI captures only"),  # DiLiGenT PNGs are linear
])  # fmt: skip
def test_options_that_a_capture_run_cannot_meet_exit_2(tmp_path, capsys, fake_solver, extra, msg):
    data = _small_dataset(tmp_path / "obj")
    code, err = _run(["ps", str(data), "--out", str(tmp_path / "res"), "--quiet", *extra], capsys)
    assert code == 2 and msg in _error_line(err), err
    assert not (tmp_path / "res").exists() and fake_solver.calls == []
    if extra[0] == "--drop-first":
        assert "2 of its 8 images left" in err
    code, err = _run(["demo", "--out", str(tmp_path / "res"), *FAST, "--linear-input"], capsys)
    assert code == 2 and "unrecognized arguments: --linear-input" in err


@pytest.mark.parametrize("argv", [["ps", "CAP", "--linear"], ["rti", "RES", "--linear"], ["demo", "--over"]])
def test_options_are_not_abbreviated(tmp_path, capsys, fake_solver, argv):
    """`--linear` is no option: a prefix would mean --linear-input in ps and --linear-output in rti."""
    code, err = _run([a.replace("CAP", str(tmp_path)).replace("RES", str(tmp_path)) for a in argv], capsys)
    assert code == 2 and f"unrecognized arguments: {argv[-1]}" in _error_line(err), err
    assert ("--linear-input" in _error_line(err)) == (argv[-1] == "--linear")  # the old name says the new one
    assert fake_solver.calls == []


def test_missing_capture_exit_2(tmp_path, capsys, fake_solver):
    code, err = _run(["ps", str(tmp_path / "nothing"), "--out", str(tmp_path / "res")], capsys)
    assert code == 2 and "argument CAPTURE:" in _error_line(err) and "does not exist" in err
    code, err = _run(["ps"], capsys)
    assert code == 2 and "CAPTURE" in err
    assert os.listdir(tmp_path) == [] and fake_solver.calls == []


def test_out_defaults_to_a_name_derived_from_the_input(tmp_path, fake_solver, monkeypatch):
    data = _small_dataset(tmp_path / "cat_capture")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    cli.run(["ps", str(data), "--quiet"])
    assert (work / "cat_capture_ps" / result_folder.MANIFEST).is_file()
    cli.run(["demo", *FAST])
    assert (work / "small_ps" / result_folder.MANIFEST).is_file()
    assert sorted(os.listdir(work)) == ["cat_capture_ps", "small_ps"]


def test_library_warnings_are_one_line(tmp_path, capsys, fake_solver):
    data = _small_dataset(tmp_path / "obj")
    (data / "mask.png").unlink()
    code, err = _run(["ps", str(data), "--out", str(tmp_path / "res"), "--quiet"], capsys)
    assert code == 0
    want = f"torch-hsh ps: warning: {data}: no mask.png; every pixel is treated as valid"
    assert want in err.splitlines() and "UserWarning" not in err and "cli.py" not in err, err
    with pytest.warns(UserWarning, match="no mask.png"):  # --debug leaves warnings to Python (here: pytest)
        code, err = _run(["ps", str(data), "--out", str(tmp_path / "res2"), "--quiet", "--debug"], capsys)
    assert code == 0 and "torch-hsh ps: warning:" not in err


def test_truncated_png_names_the_file(tmp_path, capsys, fake_solver):
    data = _small_dataset(tmp_path / "obj")
    raw = (data / "003.png").read_bytes()
    (data / "003.png").write_bytes(raw[: len(raw) // 2])
    code, err = _run(["ps", str(data), "--out", str(tmp_path / "res"), "--quiet"], capsys)
    assert code == 1 and "003.png" in err and len(err.strip().splitlines()) == 1


# --------------------------------------------------------------------------- #
# output folder: ours only with a manifest, atomic replacement
# --------------------------------------------------------------------------- #
def test_run_writes_manifest_last_and_strict_json(tmp_path, fake_solver):
    out = tmp_path / "res"
    metrics = cli.run(["demo", "--out", str(out), *FAST])
    manifest = _strict_json(out / result_folder.MANIFEST)
    assert manifest["format"] == result_folder.MANIFEST_FORMAT
    assert set(manifest["files"]) | {result_folder.MANIFEST} == set(os.listdir(out))
    for name in ("normals.npy", "coefficients.exr", "metrics.json", "normal_map.png", *FIGURES):
        assert name in manifest["files"], name
    m = _strict_json(out / "metrics.json")
    assert m["solver_info"]["noise_sigma"] is None  # NaN -> null
    assert m["pixels"] == metrics["pixels"] > 0 and m["lights"] == 8
    assert result_folder.is_result_folder(out)
    assert _leftovers(tmp_path) == []


def test_without_matplotlib_figures_are_skipped_and_said(tmp_path, capsys, fake_solver, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), "--size", "12", "--lights", "8"])
    assert "matplotlib is not installed" in capsys.readouterr().out
    assert not (out / "error_map.png").exists() and not (out / "relighting.png").exists()
    assert (out / "normal_map.png").exists()
    assert set(_strict_json(out / result_folder.MANIFEST)["files"]) | {result_folder.MANIFEST} == set(os.listdir(out))


@pytest.mark.skipif(not FIGURES, reason="needs matplotlib for error_map.png")
def test_rerun_replaces_own_result_and_drops_stale_files(tmp_path, fake_solver, capsys):
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])  # synthetic: ground truth -> error_map.png
    assert (out / "error_map.png").exists()
    first = capsys.readouterr().out
    assert "replac" not in first
    created = _strict_json(out / result_folder.MANIFEST)["created_utc"]
    data = _small_dataset(tmp_path / "obj", normals=False)  # no ground truth -> no error map
    cli.run(["ps", str(data), "--out", str(out)])
    said = capsys.readouterr().out  # the replacement is said, before the run and at its end
    assert f"--out {out} holds a torch-hsh result (of {created}); it is replaced when this run ends" in said
    assert f", replacing the result (of {created})" in said
    assert "no ground-truth normals" in said and " nan " not in said  # the table says n/a, not nan
    assert re.search(r"^HSH \(order \d\)\s+n/a\s+n/a\s+\d", said, re.M), said
    assert not (out / "error_map.png").exists()
    assert set(_strict_json(out / result_folder.MANIFEST)["files"]) | {result_folder.MANIFEST} == set(os.listdir(out))
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("user_files", [
    {"thesis.tex": "do not touch"},
    {"normals.npy": "my own normals", "metrics.json": "{}"},  # a result from before manifests, or the user's
])  # fmt: skip
def test_refuses_folders_that_are_not_ours(tmp_path, capsys, fake_solver, user_files):
    out = tmp_path / "mine"
    out.mkdir()
    for name, text in user_files.items():
        (out / name).write_text(text)
    code, err = _run(["demo", "--out", str(out), *FAST], capsys)
    assert code == 2 and "--overwrite" in err
    assert {n: (out / n).read_text() for n in user_files} == user_files and fake_solver.calls == []
    assert sorted(os.listdir(tmp_path)) == ["mine"]
    cli.run(["demo", "--out", str(out), *FAST, "--overwrite"])
    assert result_folder.is_result_folder(out) and not (out / "thesis.tex").exists()


def test_never_replaces_cwd_home_or_the_data_folder(tmp_path, capsys, fake_solver, monkeypatch):
    data = _small_dataset(tmp_path / "obj")
    monkeypatch.chdir(tmp_path)
    for out in (".", str(tmp_path.parent), str(Path.home())):
        code, err = _run(["demo", "--out", out, *FAST, "--overwrite"], capsys)
        assert code == 2 and "folder of its own" in err
    for out in (data, data / "res", tmp_path):
        code, err = _run(["ps", str(data), "--out", str(out), "--quiet", "--overwrite"], capsys)
        assert code == 2
    assert fake_solver.calls == [] and sorted(os.listdir(tmp_path)) == ["obj"]
    assert (data / "light_directions.txt").exists()


def test_a_manifest_nested_too_deeply_is_not_ours(tmp_path):
    (tmp_path / "manifest.json").write_text("[" * 100000)  # json raises RecursionError, not ValueError
    assert not result_folder.is_result_folder(tmp_path)


def test_our_result_with_a_user_file_added_is_not_ours(tmp_path, capsys, fake_solver):
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])
    (out / "notes.txt").write_text("mine")
    assert not result_folder.is_result_folder(out)
    code, err = _run(["demo", "--out", str(out), *FAST], capsys)
    assert code == 2 and (out / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("edit", ["change", "same_size"])
def test_a_user_edit_inside_our_result_is_not_overwritten(tmp_path, capsys, fake_solver, edit):
    """The manifest's SHA-256 sums are compared, not only the names: an edited file makes the folder the user's."""
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])
    p = out / "metrics.json"
    text = p.read_text()
    edited = text.replace('"lights": 8', '"lights": 9') if edit == "same_size" else text + "\n// my notes\n"
    assert edited != text and (edit != "same_size" or len(edited) == len(text))
    p.write_text(edited)
    assert not result_folder.is_result_folder(out)
    code, err = _run(["demo", "--out", str(out), *FAST, "--seed", "4"], capsys)
    assert code == 2 and "metrics.json (changed since the run)" in _error_line(err) and "--overwrite" in err
    assert p.read_text() == edited and len(fake_solver.calls) == 1
    cli.run(["demo", "--out", str(out), *FAST, "--overwrite"])
    assert result_folder.is_result_folder(out)


def test_interrupted_run_into_new_parent_folders_removes_them(tmp_path, capsys, fake_solver):
    """docs/cli.md: nothing is left behind by a run that does not finish, not even the parents it made."""
    fake_solver.state["fail_in_pictures"] = KeyboardInterrupt()
    code, _ = _run(["demo", "--out", str(tmp_path / "a" / "b" / "res"), *FAST], capsys)
    assert code == 130 and os.listdir(tmp_path) == []
    # a parent that existed before, or that something else wrote into meanwhile, stays
    (tmp_path / "keep").mkdir()
    code, _ = _run(["demo", "--out", str(tmp_path / "keep" / "new" / "res"), *FAST], capsys)
    assert code == 130 and os.listdir(tmp_path) == ["keep"] and os.listdir(tmp_path / "keep") == []
    fake_solver.state["fail_in_pictures"] = None
    cli.run(["demo", "--out", str(tmp_path / "a" / "b" / "res"), *FAST])
    assert result_folder.is_result_folder(tmp_path / "a" / "b" / "res")


@pytest.mark.skipif(not os.path.isdir("/proc/self") or (hasattr(os, "geteuid") and os.geteuid() != 0),
                    reason="as root, os.access says /proc is writable; creating in it fails")
def test_out_in_a_folder_that_refuses_new_folders_exits_2_before_the_solve(capsys, fake_solver):
    code, err = _run(["demo", "--out", "/proc/torch_hsh_x", *FAST], capsys)
    assert code == 2 and "does not accept new folders" in _error_line(err) and "--out" in _error_line(err)
    assert fake_solver.calls == []


def test_out_probe_leaves_nothing(tmp_path, capsys, fake_solver, monkeypatch):
    real = result_folder.tempfile.mkdtemp

    def refuse(*a, **k):
        if k.get("prefix", "").startswith(".torch-hsh-probe."):
            raise PermissionError(13, "Permission denied")
        return real(*a, **k)

    monkeypatch.setattr(result_folder.tempfile, "mkdtemp", refuse)
    code, err = _run(["demo", "--out", str(tmp_path / "x" / "res"), *FAST], capsys)
    assert code == 2 and "does not accept new folders (Permission denied)" in _error_line(err)
    assert os.listdir(tmp_path) == [] and fake_solver.calls == []
    monkeypatch.setattr(result_folder.tempfile, "mkdtemp", real)
    cli.run(["demo", "--out", str(tmp_path / "x" / "res"), *FAST])
    assert sorted(os.listdir(tmp_path / "x")) == ["res"]


@pytest.mark.parametrize("exc,code", [(KeyboardInterrupt(), 130), (RuntimeError("disk full"), 1)])
def test_interrupted_run_leaves_previous_result_untouched(tmp_path, capsys, fake_solver, exc, code):
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])
    before = _snapshot(out)
    fake_solver.state["fail_in_pictures"] = exc  # after normals/coefficients/metrics are staged
    got, _ = _run(["demo", "--out", str(out), *FAST, "--seed", "3"], capsys)
    assert got == code
    assert _snapshot(out) == before
    assert _leftovers(tmp_path) == []  # the staging folder is removed


def test_failed_swap_restores_the_previous_result(tmp_path, capsys, fake_solver, monkeypatch):
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])
    before = _snapshot(out)
    real_rename = os.rename
    seen = []

    def rename(src, dst):
        seen.append((Path(src).name, Path(dst).name))
        if len(seen) == 2:  # new folder into place
            raise KeyboardInterrupt
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    code, _ = _run(["demo", "--out", str(out), *FAST], capsys)
    assert code == 130
    assert _snapshot(out) == before and _leftovers(tmp_path) == []


def test_confidence_map_written_and_summarised(tmp_path, fake_solver):
    def conf(mask):
        H, W = mask.shape
        return torch.linspace(0, 1, H * W, dtype=torch.float64).reshape(H, W)

    fake_solver.state["confidence"] = conf
    out = tmp_path / "res"
    cli.run(["demo", "--out", str(out), *FAST])
    m = _strict_json(out / "metrics.json")
    mask = torch.as_tensor(synthetic_scene(12, 8)["mask"]).numpy()
    c = conf(torch.as_tensor(mask)).numpy()
    assert m["confidence"]["mean"] == pytest.approx(float(c[mask].mean()), abs=1e-12)
    assert m["confidence"]["pixels"] == int(mask.sum())
    png = _read_png(out / "confidence.png")
    assert png.dtype == np.uint8 and png.shape == mask.shape
    np.testing.assert_array_equal(png[mask], np.rint(c[mask] * 255).astype(np.uint8))
    assert "confidence.png" in _strict_json(out / result_folder.MANIFEST)["files"]


def test_no_confidence_attribute_no_file(tmp_path, fake_solver):
    cli.run(["demo", "--out", str(tmp_path / "r"), *FAST])
    assert not (tmp_path / "r" / "confidence.png").exists()
    assert "confidence" not in _strict_json(tmp_path / "r" / "metrics.json")


def test_drop_first_and_max_images(tmp_path, fake_solver):
    data = _small_dataset(tmp_path / "obj")
    m = cli.run(["ps", str(data), "--out", str(tmp_path / "r"), "--quiet", "--drop-first", "2",
                     "--max-images", "4"])
    assert m["lights"] == 4 and fake_solver.calls[-1]["lights"] == 4


def test_figures_copied(tmp_path, fake_solver):
    cli.run(["demo", "--out", str(tmp_path / "r"), *FAST, "--figures", str(tmp_path / "fig")])
    assert sorted(os.listdir(tmp_path / "fig")) == sorted(
        f"ps_{n}" for n in os.listdir(tmp_path / "r") if n.endswith(".png"))


# --------------------------------------------------------------------------- #
# the real process
# --------------------------------------------------------------------------- #
def test_python_m_torch_hsh_exit_codes(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "torch_hsh", "demo", "--holdout", "-3", "--out", str(tmp_path / "r")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2 and "--holdout" in _error_line(r.stderr) and not (tmp_path / "r").exists()
    r = subprocess.run([sys.executable, "-m", "torch_hsh", "--version"], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 0 and torch_hsh.__version__ in r.stdout


@pytest.mark.slow
def test_sigterm_leaves_no_debris_and_the_previous_result(tmp_path):
    """SIGTERM during the solve: exit 143, the previous result unchanged, no staging folder left behind."""
    import signal
    import time

    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = tmp_path / "res"
    args = [sys.executable, "-m", "torch_hsh", "demo", "--scene", "small", "--out", str(out), "--quiet"]
    subprocess.run(args + ["--size", "12", "--lights", "8"], env=env, check=True, timeout=300)
    before = _snapshot(out)
    proc = subprocess.Popen(args + ["--size", "96", "--lights", "60", "--order", "4", "--overwrite"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        while not any(n.endswith(".partial") for n in os.listdir(tmp_path)) and time.time() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        assert any(n.endswith(".partial") for n in os.listdir(tmp_path)), "the run never staged its output"
        time.sleep(0.3)  # inside the solve
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "terminated; the previous output (if any) is unchanged" in err
    assert _snapshot(out) == before and _leftovers(tmp_path) == []


# --------------------------------------------------------------------------- #
# fit
# --------------------------------------------------------------------------- #
def test_fit_merl_file(tmp_path, capsys):
    from torch_hsh.brdf import Lambertian
    from torch_hsh.io.merl import tabulate_merl, write_merl

    f = write_merl(tmp_path / "lambert.binary", tabulate_merl(Lambertian(0.5), shape=(4, 4, 8)))
    out = tmp_path / "c.npz"
    code, _ = _run(["fit", str(f), "--order", "2", "--out", str(out), "--quiet", "--method", "quadrature"], capsys)
    assert code == 0
    z = np.load(out)
    K = torch_hsh.num_isotropic(2)
    assert z["coefficients"].shape == (3, K)
    # --method quadrature is the library's projection of the file's BRDF, with its energy accuracy
    # (the default, --method samples, is tested in tests/test_fit_cli.py)
    from torch_hsh.fitting import brdf_energy, energy_accuracy, project
    from torch_hsh.io.merl import read_merl

    ref = project(read_merl(f), order=2)
    np.testing.assert_array_equal(z["coefficients"], ref.numpy())
    np.testing.assert_array_equal(z["energy_accuracy"], energy_accuracy(ref, brdf_energy(read_merl(f), 2)).numpy())
    assert abs(z["coefficients"][0, 0] - 1.0) < 0.2  # a_0 = 2 rho for a Lambertian, up to the coarse 4x4x8 table
    assert json.loads(str(z["metadata"]))["order"] == 2
    code, err = _run(["fit", str(f), "--order", "2", "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "--overwrite" in err
    (tmp_path / "bad.binary").write_bytes(b"\x01\x02")
    code, err = _run(["fit", str(tmp_path / "bad.binary"), "--out", str(tmp_path / "d.npz"), "--quiet"], capsys)
    assert code == 1 and "bad.binary" in err and not (tmp_path / "d.npz").exists()


def test_depth_mesh_and_result_file_from_a_real_solve(tmp_path):
    pytest.importorskip("trimesh")
    out = tmp_path / "surf"
    cli.run(["demo", "--out", str(out), "--scene", "small", "--size", "16", "--lights", "10", "--depth", "--mesh", "--quiet"])
    names = set(_strict_json(out / result_folder.MANIFEST)["files"])
    assert {"depth.npy", "depth.exr", "mesh.ply", "surface.png", "result.npz"} <= names
    depth = np.load(out / "depth.npy")
    res = ps.HSHResult.read(out / "result.npz")
    mask = res.mask.numpy()
    assert depth.shape == mask.shape and np.isfinite(depth[mask]).all() and np.isnan(depth[~mask]).all()
    # a sphere: the centre is the highest point of the integrated surface
    assert depth[mask].max() - depth[8, 8] < 0.2 * (depth[mask].max() - depth[mask].min())
    assert _strict_json(out / "metrics.json")["surface"]["components"] == 1


def test_default_scene_is_the_demo_scene(tmp_path, fake_solver):
    out = tmp_path / "demo"
    cli.run(["demo", "--out", str(out), "--size", "24", "--lights", "12", "--quiet"])
    m = _strict_json(out / "metrics.json")
    assert "bumpy" in m["data"].lower() or "demo" in m["data"].lower()
    assert m["lights"] == 12


def test_flattened_starts_flag_reaches_the_solver(tmp_path, capsys, fake_solver):
    code, _ = _run(["demo", "--out", str(tmp_path / "a"), *FAST], capsys)
    assert code == 0 and "calibration_starts" not in fake_solver.calls[-1]
    code, _ = _run(["demo", "--out", str(tmp_path / "b"), *FAST, "--flattened-starts"], capsys)
    assert code == 0
    assert fake_solver.calls[-1]["calibration_starts"] == ("lambertian", "independent", "flattened")


def test_basis_ridge_flag_reaches_the_solver_and_is_checked(tmp_path, capsys, fake_solver):
    code, _ = _run(["demo", "--out", str(tmp_path / "a"), *FAST], capsys)
    assert code == 0 and fake_solver.calls[-1]["basis_ridge"] == ps.DEFAULT_BASIS_RIDGE
    code, _ = _run(["demo", "--out", str(tmp_path / "b"), *FAST, "--basis-ridge", "0.01"], capsys)
    assert code == 0 and fake_solver.calls[-1]["basis_ridge"] == 0.01
    for bad in ("0", "-1", "nan", "2", "abc"):
        with pytest.raises(SystemExit):
            cli.main(["demo", "--out", str(tmp_path / "c"), *FAST, "--basis-ridge", bad])
        assert "--basis-ridge" in capsys.readouterr().err


def test_holdout_uses_the_same_solver_options(tmp_path, capsys, fake_solver, monkeypatch):
    seen = {}

    def holdout(images, lights, intensities=None, mask=None, holdout=10, seed=0, **kw):
        seen.update(kw, holdout=holdout)
        return SimpleNamespace(test_indices=torch.arange(holdout), relative_rmse=0.1, rmse=0.01,
                               lambertian_relative_rmse=0.2)

    monkeypatch.setattr(ps, "holdout_evaluation", holdout)
    code, _ = _run(["demo", "--out", str(tmp_path / "h"), *FAST, "--holdout", "2", "--basis-ridge", "0.01",
                    "--flattened-starts"], capsys)
    assert code == 0 and seen["holdout"] == 2
    assert seen["basis_ridge"] == 0.01 and seen["calibration_starts"] == ("lambertian", "independent", "flattened")


def test_refine_surface_flag_reaches_the_solver(tmp_path, capsys, fake_solver):
    code, _ = _run(["demo", "--out", str(tmp_path / "a"), *FAST], capsys)
    assert code == 0 and fake_solver.calls[-1].get("refine_surface", 0) == 0
    code, _ = _run(["demo", "--out", str(tmp_path / "b"), *FAST, "--refine-surface"], capsys)
    assert code == 0 and fake_solver.calls[-1]["refine_surface"] == ps.settings.SURFACE_ROUNDS


def test_depth_of_the_whole_surface_stage_is_written_as_is(tmp_path, capsys):
    # a real solve with the stage: --depth writes the stage's own depth map, not a re-integration
    code, _ = _run(["demo", "--out", str(tmp_path / "r"), "--scene", "small", "--size", "24", "--lights", "12",
                    "--refine-surface", "--depth"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "whole-surface stage" in out.out
    # the stages after the solve say what their safeguards decided: the surface stage, and the
    # interreflection round that comes with it
    assert "whole-surface stage: kept" in out.out or "whole-surface stage: rejected" in out.out
    assert "interreflections: one bounce" in out.out
    res = ps.HSHResult.read(tmp_path / "r" / "result.npz")
    depth = np.load(tmp_path / "r" / "depth.npy")
    m = res.mask.numpy()
    assert res.depth is not None and np.allclose(depth[m], res.depth.numpy()[m], rtol=1e-6)
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["surface"]["integrator"] == "whole-surface stage"


def test_stage_report_names_each_decision():
    from torch_hsh.ps.cli import _stage_report

    assert _stage_report({}) == []
    lines = _stage_report({"interreflection_accepted": 0.0, "interreflection_fraction": 0.007,
                           "interreflection_confidence_before": 0.95, "interreflection_confidence_after": 0.94,
                           "interreflection_time_s": 4.7, "surface_accepted": 1.0, "surface_heldout_before": 0.0348,
                           "surface_heldout_after": 0.0347, "surface_time_s": 21.9})
    assert len(lines) == 2
    assert "rejected, the first solve is returned" in lines[0] and "0.70% of the light" in lines[0]
    assert "0.9500 -> 0.9400" in lines[0]
    assert lines[1].startswith("whole-surface stage: kept") and "0.0348 -> 0.0347" in lines[1]
