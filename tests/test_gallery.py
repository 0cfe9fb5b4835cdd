"""The gallery scripts (examples/gallery/plot_*.py, built into docs/gallery by sphinx-gallery at
``make docs``) run as plain scripts: each, run in a temporary folder with the Agg backend, finishes
and draws at least one figure. The viewer's script also gives a picture without Chromium (it shows
the committed screenshot then)."""
import runpy
import shutil
from pathlib import Path

import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

GALLERY = Path(__file__).resolve().parents[1] / "examples" / "gallery"
SCRIPTS = sorted(GALLERY.glob("plot_*.py"))

pytestmark = pytest.mark.slow  # about 30 s for the five scripts on one loaded core


def _run(script: Path, tmp_path, monkeypatch) -> list:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setattr(plt, "show", lambda *a, **k: None)
    plt.close("all")
    try:
        runpy.run_path(str(script), run_name="__main__")
        figures = [plt.figure(n) for n in plt.get_fignums()]
        for k, fig in enumerate(figures):  # every figure draws
            fig.savefig(tmp_path / f"figure_{k}.png", dpi=40)
        return figures
    finally:
        plt.close("all")


def test_there_are_gallery_scripts():
    assert {s.name for s in SCRIPTS} >= {"plot_photometric_stereo.py", "plot_relighting.py", "plot_brdf_lobes.py",
                                         "plot_environment_lighting.py", "plot_viewer.py"}
    assert (GALLERY / "GALLERY_HEADER.rst").exists()
    for s in SCRIPTS:  # a sphinx-gallery header: a docstring with a title underlined by '='
        lines = s.read_text().split('"""')[1].strip().splitlines()
        assert len(lines) > 2 and set(lines[1]) == {"="} and len(lines[1]) >= len(lines[0]), s.name


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda s: s.stem)
def test_gallery_script_runs_and_draws(script, tmp_path, monkeypatch):
    figures = _run(script, tmp_path, monkeypatch)
    assert figures, f"{script.name} drew no figure"


def test_viewer_script_without_chromium(tmp_path, monkeypatch):
    """No Chromium on the PATH: the committed screenshot, one figure, no failure."""
    which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None if "chrom" in name else which(name, *a, **k))
    figures = _run(GALLERY / "plot_viewer.py", tmp_path, monkeypatch)
    assert len(figures) == 1
    assert "committed screenshot" in figures[0].axes[0].get_title()
