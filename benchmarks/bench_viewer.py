"""Time to the first frame of the relighting viewer (``torch-hsh view``) in headless Chromium (issue 24).

Writes the viewer of a DiLiGenT-size result (612 x 512, the sphere of ``scenes.sphere_normals``
with radius 0.8 covering 40 % of the image, order 3, random coefficients: incompressible, the
largest file such a result gives) and opens it in headless Chromium with SwiftShader WebGL2, as
``tests/test_viewer.py`` does, ``--repeats`` times, each with a fresh profile. The page records
when its first frame is drawn (``data-first-frame-ms`` on ``document.body`` and one
``console.info`` line, see :mod:`torch_hsh.rti.viewer`); Chromium logs the line on stderr, where this
script reads it. No virtual time: ``--virtual-time-budget`` would stop the page's clock.

Per run, a line as soon as it is measured:

* start-up: from launching ``chromium`` to the page's navigation start (``performance.timeOrigin``);
* page: from the navigation start to the first frame (read and parse the HTML with its embedded
  data, inflate the coefficient planes, compile the shader, upload, draw, wait for the GPU), with
  its stages: ``script`` (the HTML parsed), ``decoded`` (planes inflated), ``first frame``;
* total: from the launch to the moment the line reached this script.

Then the medians and the 1-minute load average before and after (the numbers depend on the load of
the machine). Run: ``python benchmarks/bench_viewer.py [--repeats 5] [--chromium PATH]``;
``--quick`` (CI, ``tests/test_viewer.py``): a 64 x 64 result, 2 runs.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import os
import queue
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from torch_hsh.render import scenes
from torch_hsh.ps import HSHResult
from torch_hsh.rti.viewer import write_viewer

print = functools.partial(print, flush=True)  # a line per run as it is measured

LINE = re.compile(r"torch_hsh viewer: first frame ([\d.]+) ms \(script ([\d.]+) ms, base64 ([\d.]+) ms, decoded ([\d.]+) ms\) "
                  r"after navigation start ([\d.]+)")


def diligent_size_result(H: int = 512, W: int = 612, order: int = 3) -> HSHResult:
    """The result of ``tests/test_viewer.py::test_diligent_size_file_is_under_30_mb``."""
    K = (order + 1) * (order + 2) * (order + 3) // 6
    n, m = scenes.sphere_normals((H, W), radius=0.8, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(H, W, 3, K, generator=g) * 0.05
    a[..., 0] += 1.0
    return HSHResult(normals=n, coefficients=a * m[..., None, None], albedo=torch.rand(H, W, 3, generator=g),
                     residual=torch.rand(H, W, generator=g), weights=torch.zeros(H, W, 0), mask=m, order=order,
                     lights=torch.eye(3), runtime_s=0.0)


@contextlib.contextmanager
def _chromium_profile():
    """A temporary Chromium profile folder. Chromium's helper processes can still write into it for a moment
    after the browser has exited, so the removal retries and then gives up quietly (a folder left in the
    temporary directory, never a failed benchmark; CI once failed on 'Directory not empty')."""
    profile = tempfile.mkdtemp(prefix="torch_hsh_chromium_")
    try:
        yield profile
    finally:
        for _ in range(20):
            try:
                shutil.rmtree(profile)
                break
            except OSError:
                time.sleep(0.25)
        else:
            shutil.rmtree(profile, ignore_errors=True)


def first_frame(chromium: str, html: Path, width: int, height: int, timeout: float = 120.0) -> dict:
    """Open ``html`` in a fresh headless Chromium; the times (s) to its first frame, read from its console line."""
    with _chromium_profile() as profile:
        cmd = [chromium, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
               "--enable-logging=stderr", "--v=0", "--no-first-run", f"--user-data-dir={profile}",
               "--force-device-scale-factor=1", f"--window-size={width},{height + 40}", html.resolve().as_uri()]
        lines: "queue.Queue[str]" = queue.Queue()
        t_launch = time.time()
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, errors="replace")

        def pump():
            assert p.stderr is not None
            for line in p.stderr:
                lines.put(line)
            lines.put("")

        threading.Thread(target=pump, daemon=True).start()
        tail = []
        try:
            while True:
                try:
                    line = lines.get(timeout=max(0.0, t_launch + timeout - time.time()))
                except queue.Empty:
                    raise TimeoutError(f"no first frame within {timeout} s:\n" + "".join(tail[-20:])) from None
                if not line:
                    raise RuntimeError(f"Chromium exited (status {p.wait()}) before the first frame:\n"
                                       + "".join(tail[-20:]))
                tail.append(line)
                m = LINE.search(line)
                if m:
                    t_seen = time.time()
                    frame, script, b64, decoded, origin = (float(x) for x in m.groups())
                    break
                if "CONSOLE" in line and "error" in line.lower():
                    raise RuntimeError(f"the page failed: {line.strip()}")
        finally:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    startup = origin / 1000 - t_launch
    return {"startup": startup, "script": script / 1000, "base64": b64 / 1000, "decoded": decoded / 1000, "page": frame / 1000,
            "total": t_seen - t_launch}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=None, help="browser runs (default 5; 2 with --quick)")
    ap.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                    help="result size (default 512 612, DiLiGenT; 64 64 with --quick)")
    ap.add_argument("--chromium", default=None, help="Chromium binary (default: chromium on the PATH)")
    ap.add_argument("--quick", action="store_true", help="the CI run: a 64 x 64 result, 2 runs")
    a = ap.parse_args()
    repeats = a.repeats or (2 if a.quick else 5)
    H, W = a.size or ((64, 64) if a.quick else (512, 612))
    chromium = a.chromium or next((shutil.which(c) for c in ("chromium", "chromium-browser", "google-chrome")
                                   if shutil.which(c)), None)
    if chromium is None:
        sys.exit("no Chromium found (apt-get install chromium, or --chromium PATH)")
    torch.set_num_threads(1)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        html = Path(tmp) / "viewer.html"
        t = time.perf_counter()
        res = diligent_size_result(H, W)
        write_viewer(html, res, exposure=1.0)
        size = html.stat().st_size
        print(f"viewer of a {W} x {H} result ({float(res.mask.float().mean()):.0%} masked, order {res.order}, "
              f"random coefficients): {size / 2 ** 20:.2f} MiB, written in {time.perf_counter() - t:.1f} s; "
              f"{os.cpu_count()} CPUs, load average {load0:.2f}")
        runs = []
        for i in range(repeats):
            r = first_frame(chromium, html, W, H)
            runs.append(r)
            print(f"run {i + 1}/{repeats}: start-up {r['startup']:.2f} s + page {r['page']:.2f} s "
                  f"(script {r['script']:.2f} s, base64 {r['base64']:.2f} s, decoded {r['decoded']:.2f} s, first frame {r['page']:.2f} s) "
                  f"= total {r['total']:.2f} s")
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    print(f"median of {repeats}: start-up {med['startup']:.2f} s, page to first frame {med['page']:.2f} s "
          f"(script {med['script']:.2f} s, base64 {med['base64']:.2f} s, decoded {med['decoded']:.2f} s), total {med['total']:.2f} s; "
          f"load average {load0:.2f} before, {os.getloadavg()[0]:.2f} after")


if __name__ == "__main__":
    main()
