"""Interrupted writers: the sweep of a killed run's temporaries (torch_hsh._atomic), SIGTERM on the CLI, and the
short form of the kill campaign (tools/kill_campaign.py; `make kill` runs the full one)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from torch_hsh._atomic import atomic_file, replace_folder, staged_folder, sweep

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


@pytest.fixture(scope="module")
def dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_sweep_removes_a_dead_writers_temporaries_only(tmp_path, dead_pid):
    target = tmp_path / "out.npz"
    target.write_bytes(b"old")
    stale_file = tmp_path / f".out.npz.{dead_pid}.0123abcd.partial"
    stale_file.write_bytes(b"half")
    stale_dir = tmp_path / f".out.npz.{dead_pid}.89abcdef.partial"
    stale_dir.mkdir()
    (stale_dir / "a").write_bytes(b"x")
    live = tmp_path / f".out.npz.{os.getppid()}.0123abcd.partial"  # a running process's
    live.write_bytes(b"writing")
    users = [".out.npz.partial", "out.npz.partial", f".out.npz.{dead_pid}.partial", f".other.{dead_pid}.0123abcd.partial",
             f".out.npz.{dead_pid}.0123abcd.partial.keep", f".out.npz.{dead_pid}.0123ABCD.partial"]
    for name in users:
        (tmp_path / name).write_bytes(b"mine")
    sweep(target)
    assert sorted(os.listdir(tmp_path)) == sorted(users + ["out.npz", live.name])
    assert target.read_bytes() == b"old" and all((tmp_path / n).read_bytes() == b"mine" for n in users)


def test_sweep_puts_back_an_old_folder_left_between_the_two_renames(tmp_path, dead_pid):
    old = tmp_path / f".res.{dead_pid}.0123abcd.old"
    old.mkdir()
    (old / "result.npz").write_bytes(b"old result")
    new = tmp_path / f".res.{dead_pid}.89abcdef.partial"
    new.mkdir()
    sweep(tmp_path / "res")  # the target is missing: the old result comes back, the staged one goes
    assert os.listdir(tmp_path) == ["res"] and (tmp_path / "res" / "result.npz").read_bytes() == b"old result"
    old.mkdir()  # killed while removing the old folder after the swap: the new one stays
    sweep(tmp_path / "res")
    assert os.listdir(tmp_path) == ["res"] and (tmp_path / "res" / "result.npz").read_bytes() == b"old result"


def test_atomic_writes_leave_the_target_or_the_new_content(tmp_path):
    target = tmp_path / "a.txt"
    with atomic_file(target) as tmp:
        tmp.write_text("one")
    with pytest.raises(KeyboardInterrupt), atomic_file(target) as tmp:
        tmp.write_text("two")
        raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["a.txt"] and target.read_text() == "one"
    with staged_folder(tmp_path / "d") as d:
        (d / "f").write_text("1")
    with pytest.raises(RuntimeError), staged_folder(tmp_path / "d") as d:
        (d / "f").write_text("2")
        raise RuntimeError
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "d"] and (tmp_path / "d" / "f").read_text() == "1"
    (tmp_path / "e").mkdir()
    replace_folder(tmp_path / "e", tmp_path / "d")
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "d"] and os.listdir(tmp_path / "d") == []


@pytest.mark.skipif(not hasattr(signal, "SIGTERM") or os.name != "posix", reason="POSIX signals")
def test_sigterm_during_the_relight_export_exits_143_and_leaves_the_old_folder(tmp_path):
    """A real ``torch-hsh rti`` process that receives SIGTERM while its staging folder is half written."""
    from torch_hsh import cli
    from torch_hsh.rti.synthetic import write_synthetic_capture

    cap = write_synthetic_capture(tmp_path / "cap", 12, 10, 6)
    cli.run(["ps", str(cap), "--out", str(tmp_path / "res"), "--quiet", "--threads", "1", "--order", "2"])
    out = tmp_path / "out" / "relight"
    cli.run(["rti", str(tmp_path / "res"), "--relight", str(out), "--quiet", "--threads", "1"])
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    script = textwrap.dedent(f"""
        import os, signal, sys
        import torch_hsh.rti.io as io
        write = io._write_tile
        def write_then_terminated(path, *a):  # the first plane written, then SIGTERM
            write(path, *a)
            os.kill(os.getpid(), signal.SIGTERM)
        io._write_tile = write_then_terminated
        from torch_hsh import cli
        sys.exit(cli.main(["rti", {str(tmp_path / "res")!r}, "--relight", {str(out)!r}, "--overwrite", "--quiet",
                           "--exposure", "2"]))
    """)
    r = subprocess.run([sys.executable, "-c", script], env=ENV, capture_output=True, text=True, timeout=300)
    assert r.returncode == 143 and "terminated; the previous output (if any) is unchanged" in r.stderr, r.stderr
    assert os.listdir(out.parent) == ["relight"] and {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "fork"), reason="the campaign forks its runs")
def test_kill_campaign_short_form():
    """Two kills per writer (a SIGTERM and a SIGKILL at random moments): nothing lost, no debris."""
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "kill_campaign.py"), "--kills", "2", "--seed", "1"],
                       env=ENV, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "10 kills: no result lost, no debris" in r.stdout, r.stdout + r.stderr


def test_relight_folder_is_replaced_as_a_whole_but_never_over_a_users_file(tmp_path):
    import numpy as np

    from torch_hsh.rti.io import save_relight

    c = np.random.default_rng(0).uniform(-1, 1, (6, 5, 3, 9))
    folder = save_relight(tmp_path / "r", c)
    save_relight(folder, c, layout="deepzoom", overwrite=True)  # an image-layout folder replaced as a whole
    assert not (folder / "plane_0.jpg").exists() and (folder / "plane_0.dzi").exists()
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="notes.txt"):
        save_relight(folder, c, overwrite=True)
    assert (folder / "notes.txt").read_text() == "mine" and sorted(os.listdir(tmp_path)) == ["r"]
