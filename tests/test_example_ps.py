"""End-to-end check of the README demo (examples/photometric_stereo.py) and its output contract."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load_example():
    spec = importlib.util.spec_from_file_location("ps_example", ROOT / "examples" / "photometric_stereo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
@pytest.mark.parametrize("materials", ["2", "0", "auto"])
def test_demo_output_contract(tmp_path, materials):
    mod = _load_example()
    out = tmp_path / "out"
    metrics = mod.main(["--out", str(out), "--scene", "small", "--size", "28", "--lights", "24", "--materials", materials])
    for name in ("normals.npy", "coefficients.exr", "metrics.json", "normal_map.png", "error_map.png", "relighting.png"):
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    for key in ("method", "order", "pixels", "lights", "runtime_s", "mean_angular_error_deg",
                "median_angular_error_deg", "lambertian_mean_angular_error_deg"):
        assert key in m, key
    assert m["materials"] == {"0": None, "auto": "auto"}.get(materials, int(materials) if materials.isdigit() else None)
    if materials == "auto":  # the choice and the criterion are reported
        info = m["solver_info"]
        assert info["materials_chosen"] in (1, 2, 3, 4) and len(info["materials_criterion"]) == 4
    n = np.load(out / "normals.npy")
    assert n.dtype == np.float32 and n.shape == (28, 28, 3)
    # the non-Lambertian solver beats Lambertian least squares on the analytic-BRDF scene
    assert m["mean_angular_error_deg"] < m["lambertian_mean_angular_error_deg"]
    assert metrics["pixels"] == m["pixels"]


def test_demo_refuses_foreign_output_folder(tmp_path):
    mod = _load_example()
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("do not touch")
    with pytest.raises(SystemExit):
        mod.main(["--out", str(out), "--scene", "small", "--size", "16", "--lights", "12"])
    assert (out / "thesis.tex").read_text() == "do not touch"
