"""Tests for torch_hsh.rti.viewer / ``torch-hsh view``: the generated GLSL basis equals the library's
isotropic Helmholtz basis, and screenshots of the page in a real headless Chromium (SwiftShader
WebGL2) match the library's own render at three light directions (< 2/255 RMS inside the mask); the
page's layout and its light, zoom and pan controls, driven in headless Chromium through the DevTools
protocol (mouse wheel and drags as a user makes them).

The browser tests skip, saying so, where no Chromium is installed (``apt-get install chromium``).
"""
import base64
import io
import json
import os
import shutil
import subprocess
import tempfile
import time

import numpy as np
import pytest
import torch

from torch_hsh import cli, helmholtz_isotropic_world

from torch_hsh.render import scenes
from torch_hsh.rti.io import srgb_encode
from torch_hsh.ps import HSHResult
from torch_hsh.rti.viewer import _eval_program, glsl_isotropic_basis, write_viewer

CHROMIUM = next((shutil.which(c) for c in ("chromium", "chromium-browser", "google-chrome") if shutil.which(c)), None)
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (apt-get install chromium); "
                                                             "the browser tests of the viewer are skipped")
LIGHTS = ([0.3, -0.2, 0.933], [-0.5, 0.4, 0.768], [0.1, 0.7, 0.707])


@pytest.mark.parametrize("order", [0, 1, 2, 3, 4])
def test_generated_basis_equals_the_library_basis(order):
    g = torch.Generator().manual_seed(order)
    n = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64)
                                      + torch.tensor([0, 0, 1.5]), dim=-1)
    lt = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64)
                                       + torch.tensor([0, 0, 1.5]), dim=-1)
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(300, 3)
    ref = helmholtz_isotropic_world(lt, v, n, order).numpy()
    zi = (n * lt).sum(-1).clamp(0, 1).numpy()
    zo = n[:, 2].clamp(0, 1).numpy()
    B = _eval_program(order, zi, zo, lt[:, 2].numpy() - zi * zo, (1 - zi ** 2) * (1 - zo ** 2),
                      np.sqrt(zi / (1 + zi)) * np.sqrt(zo / (1 + zo)))
    ok = (zi > 0) & (zo > 0)
    np.testing.assert_allclose(B[ok], ref[ok], atol=1e-12)
    K = (order + 1) * (order + 2) * (order + 3) // 6
    assert f"out float B[{K}]" in glsl_isotropic_basis(order)


def _result(size=40):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_rti import material_scene

    n, m, a = material_scene(size)
    a = a * m[..., None, None]
    n = n * m[..., None]
    g = torch.Generator().manual_seed(0)
    return HSHResult(normals=n, coefficients=a, albedo=a[..., 0] / 2, weights=torch.zeros(size, size, 0),
                     residual=torch.rand(size, size, generator=g, dtype=torch.float64) * m, mask=m, order=4,
                     lights=torch.eye(3, dtype=torch.float64), runtime_s=0.0,
                     confidence=torch.rand(size, size, generator=g, dtype=torch.float64) * m)


_CHROMIUM_HUNG = []  # set once a headless Chromium did not finish a screenshot: the later shots skip at once


def _shot(html, w, h, light, mode, out):
    """Screenshot of the viewer page. Some Chromium builds never finish a SwiftShader WebGL2 page under
    --virtual-time-budget (seen with Debian's Chromium on a machine without a GPU, also on a blank page): that is
    a missing tool, as when Chromium is absent, so the test skips and says so."""
    if _CHROMIUM_HUNG:
        pytest.skip(_CHROMIUM_HUNG[0])
    url = f"file://{html}#light={light[0]:.6f},{light[1]:.6f},{light[2]:.6f}&mode={mode}"
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
           "--force-device-scale-factor=1", "--hide-scrollbars", f"--window-size={w},{h}",
           "--virtual-time-budget=5000", f"--screenshot={out}", url]
    t = time.perf_counter()
    try:
        subprocess.run(cmd, capture_output=True, timeout=90, check=True)
    except subprocess.TimeoutExpired:
        _CHROMIUM_HUNG.append(f"headless {CHROMIUM} did not finish a WebGL2 screenshot in 90 s on this machine")
        pytest.skip(_CHROMIUM_HUNG[0])
    from PIL import Image

    return np.asarray(Image.open(out).convert("RGB")) / 255.0, time.perf_counter() - t


@needs_chromium
def test_screenshots_match_the_library_render(tmp_path):
    res = _result()
    html = tmp_path / "v.html"
    exposure = write_viewer(html, res)
    m = res.mask.numpy()
    for li in LIGHTS:
        lt = torch.tensor([li], dtype=torch.float64)
        lt = lt / lt.norm()
        shot, _ = _shot(html, 40, 40, lt[0].tolist(), "relit", tmp_path / "s.png")
        ref = srgb_encode(np.clip(exposure * res.relight(lt)[0].numpy(), 0, 1))
        d = (shot - ref)[m]
        assert np.sqrt((d ** 2).mean()) < 2 / 255, np.sqrt((d ** 2).mean()) * 255
        assert shot[~m].max() == 0  # black outside the mask
    shot, _ = _shot(html, 40, 40, (0, 0, 1), "normals", tmp_path / "n.png")
    np.testing.assert_allclose(shot[m], (res.normals.numpy()[m] + 1) / 2, atol=1.5 / 255)
    shot, _ = _shot(html, 40, 40, (0, 0, 1), "confidence", tmp_path / "c.png")
    np.testing.assert_allclose(shot[m][:, 0], res.confidence.numpy()[m], atol=1.5 / 255)


def test_view_cli_and_size_limit(tmp_path, capsys):
    res = _result(24)
    res.write(tmp_path / "result.npz")
    out = tmp_path / "r.html"
    assert cli.main(["view", str(tmp_path), "--out", str(out), "--quiet"]) == 0
    text = out.read_text()
    assert "http://" not in text and "https://" not in text and "#version 300 es" in text
    with pytest.raises(SystemExit) as e:
        cli.main(["view", str(tmp_path), "--out", str(out), "--quiet"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        cli.main(["view", str(tmp_path / "missing"), "--out", str(tmp_path / "x.html"), "--quiet"])
    assert e.value.code == 1 and "missing" in capsys.readouterr().err
    with pytest.raises(ValueError, match="MiB"):
        write_viewer(tmp_path / "big.html", res, max_bytes=1000)


def test_view_out_defaults_to_the_result_name_beside_it(tmp_path):
    folder = tmp_path / "cat_ps"
    folder.mkdir()
    _result(24).write(folder / "result.npz")
    assert cli.main(["view", str(folder), "--quiet"]) == 0
    assert (tmp_path / "cat_ps.html").is_file() and not list(folder.glob("*.html"))
    assert cli.main(["view", str(folder / "result.npz"), "--quiet", "--overwrite"]) == 0
    other = tmp_path / "model.npz"
    _result(24).write(other)
    assert cli.main(["view", str(other), "--quiet"]) == 0 and (tmp_path / "model.html").is_file()


def test_diligent_size_file_is_under_30_mb(tmp_path):
    """A 612 x 512 result (DiLiGenT size), 40 % of it masked, order 3: the file stays below 30 MiB."""
    H, W = 512, 612
    n, m = scenes.sphere_normals((H, W), radius=0.8, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(H, W, 3, 20, generator=g) * 0.05
    a[..., 0] += 1.0
    res = HSHResult(normals=n, coefficients=a * m[..., None, None], albedo=torch.rand(H, W, 3, generator=g),
                    residual=torch.rand(H, W, generator=g), weights=torch.zeros(H, W, 0), mask=m, order=3,
                    lights=torch.eye(3), runtime_s=0.0)
    write_viewer(tmp_path / "d.html", res, exposure=1.0)
    assert (tmp_path / "d.html").stat().st_size < 30 * 2 ** 20


@needs_chromium
def test_first_frame_times_are_recorded(tmp_path):
    """The page records when its first frame is drawn on ``document.body`` (read here with ``--dump-dom``;
    ``--virtual-time-budget`` stops the page's clock while it waits, so only the order of the stages and the
    time origin are checked: the real times come from ``benchmarks/bench_viewer.py``)."""
    import re

    html = tmp_path / "v.html"
    write_viewer(html, _result(24))
    t0 = time.time()
    out = subprocess.run([CHROMIUM, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader",
                          "--use-angle=swiftshader", "--virtual-time-budget=5000", "--dump-dom", html.as_uri()],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    body = re.search(r"<body[^>]*>", out)
    assert body, out[:2000]
    ds = {k: float(v) for k, v in re.findall(r'data-([a-z0-9-]+)="([^"]*)"', body.group(0))}
    assert set(ds) == {"script-ms", "base64-ms", "decoded-ms", "first-frame-ms", "time-origin"}, body.group(0)
    assert 0 < ds["script-ms"] <= ds["base64-ms"] <= ds["decoded-ms"] <= ds["first-frame-ms"], ds
    assert t0 - 1 < ds["time-origin"] / 1000 < time.time(), (t0, ds)  # navigation started after the launch


@needs_chromium
@pytest.mark.slow
def test_bench_viewer_quick():
    """``benchmarks/bench_viewer.py --quick``: a line per browser run as it ends, with the stages in order and
    consistent with the total, and the medians of the runs."""
    import re

    from _scripts import run_script

    r = run_script("benchmarks/bench_viewer.py", "--quick", timeout=300)
    m = re.search(r"viewer of a 64 x 64 result .*: ([\d.]+) MiB", r.stdout)
    assert m and 0 < float(m.group(1)) < 30, r.stdout
    num = r"([\d.]+)"
    runs = [tuple(float(x) for x in g.groups()) for g in re.finditer(
        rf"^run \d/2: start-up {num} s \+ page {num} s \(script {num} s, base64 {num} s, decoded {num} s, "
        rf"first frame {num} s\) = total {num} s$", r.stdout, re.M)]
    assert len(runs) == 2, r.stdout
    for startup, page, script, b64, decoded, frame, total in runs:
        assert 0 < startup < 30 and 0 < script <= b64 <= decoded <= frame == page < 30, runs
        assert startup + page <= total + 0.02 < startup + page + 5, runs  # the line is read after the frame
    m = re.search(rf"median of 2: start-up {num} s, page to first frame {num} s .* total {num} s", r.stdout)
    assert m and float(m.group(2)) == pytest.approx((runs[0][1] + runs[1][1]) / 2, abs=0.011), r.stdout
    assert r.first(r"^median") - r.first(r"^run 1/2") > 0.2  # printed as it goes


def test_page_has_a_title_a_help_line_and_a_light_widget(tmp_path):
    html = tmp_path / "v.html"
    write_viewer(html, _result(16), title="torch_hsh: scan <3> & co")
    text = html.read_text()
    assert "<title>torch_hsh: scan &lt;3&gt; &amp; co</title>" in text  # escaped
    h1 = text[text.index('<h1 id="title">'):text.index("</h1>")]
    assert "scan &lt;3&gt; &amp; co" in h1
    help_line = text[text.index('<p id="help">'):text.index("</p>", text.index('<p id="help">'))].lower()
    for words in ("drag</b> on the image", "to move the light", "scroll", "zoom", "shift-drag", "pan", "fit"):
        assert words in help_line, (words, help_line)
    for element in ('id="lightpad"', 'id="lightdot"', 'id="zin"', 'id="zout"', 'id="fit"', 'id="pan"'):
        assert element in text, element
    write_viewer(html, _result(16), title="__DATA__ plain", overwrite=True)  # a placeholder's name in the title stays
    assert '<h1 id="title">__DATA__ plain</h1>' in html.read_text()


class _DevToolsPage:
    """The viewer page in a headless Chromium driven through the DevTools protocol over a pipe
    (``--remote-debugging-pipe``: commands on the browser's fd 3, replies on its fd 4, NUL-terminated JSON): no
    virtual time (which some Chromium builds never finish with SwiftShader WebGL2, see :func:`_shot`), the first
    frame awaited by polling ``document.body.dataset.firstFrameMs``, screenshots and real mouse events."""

    def __init__(self, url, width, height, timeout=60.0):
        self.profile = tempfile.mkdtemp(prefix="torch_hsh_cdp_")
        r_in, w_in = os.pipe()
        r_out, w_out = os.pipe()

        def child():  # the pipe ends to fds 3 and 4, moved out of the way first (they may be 3 or 4 already)
            import fcntl

            a, b = fcntl.fcntl(r_in, fcntl.F_DUPFD, 10), fcntl.fcntl(w_out, fcntl.F_DUPFD, 10)
            os.dup2(a, 3)
            os.dup2(b, 4)

        cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
               "--remote-debugging-pipe", "--no-first-run", f"--user-data-dir={self.profile}", "--hide-scrollbars",
               "--force-device-scale-factor=1", f"--window-size={width},{height}", "about:blank"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, close_fds=False, preexec_fn=child)
        os.close(r_in)
        os.close(w_out)
        self.w, self.r = os.fdopen(w_in, "wb", buffering=0), os.fdopen(r_out, "rb", buffering=0)
        self.buf, self.n, self.timeout, self.session = b"", 0, timeout, None
        try:
            target = next(t["targetId"] for t in self.send("Target.getTargets")["targetInfos"] if t["type"] == "page")
            self.session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            self.send("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)
            self.send("Page.navigate", url=url)
            t_end = time.time() + timeout
            while not self.eval("document.body && document.body.dataset.firstFrameMs || ''"):
                if time.time() > t_end:
                    raise TimeoutError("no first frame: " + str(self.eval(
                        "(document.getElementById('info') || {}).textContent")))
                time.sleep(0.05)
        except BaseException:
            self.close()
            raise

    def send(self, method, **params):
        self.n += 1
        msg = {"id": self.n, "method": method, "params": params}
        if self.session:
            msg["sessionId"] = self.session
        self.w.write(json.dumps(msg).encode() + b"\0")
        t_end = time.time() + self.timeout
        while True:
            while b"\0" not in self.buf:
                if time.time() > t_end:
                    raise TimeoutError(method)
                chunk = self.r.read(1 << 16)
                if not chunk:
                    raise RuntimeError(f"Chromium closed the DevTools pipe ({method})")
                self.buf += chunk
            line, self.buf = self.buf.split(b"\0", 1)
            reply = json.loads(line)
            if reply.get("id") == self.n:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def eval(self, expr):
        r = self.send("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(str(r["exceptionDetails"]))
        return r["result"].get("value")

    def screenshot(self, path=None):
        from PIL import Image

        data = base64.b64decode(self.send("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            path.write_bytes(data)
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB")) / 255.0

    def mouse(self, kind, x, y, **kw):
        self.send("Input.dispatchMouseEvent", type=kind, x=float(x), y=float(y), **kw)

    def drag(self, x0, y0, x1, y1, modifiers=0, steps=4):
        self.mouse("mousePressed", x0, y0, button="left", buttons=1, clickCount=1, modifiers=modifiers)
        for k in range(1, steps + 1):
            self.mouse("mouseMoved", x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps, button="left",
                       buttons=1, modifiers=modifiers)
        self.mouse("mouseReleased", x1, y1, button="left", buttons=0, clickCount=1, modifiers=modifiers)

    def view(self):
        """(s, tx, ty) of the canvas's transform, and the top left of #view on the page."""
        s, tx, ty = (float(v) for v in self.eval("document.getElementById('c').dataset.view").split(","))
        left, top = self.eval("(r => [r.left, r.top])(document.getElementById('view').getBoundingClientRect())")
        return s, tx + left, ty + top

    def close(self):
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for f in (self.w, self.r):
            f.close()
        shutil.rmtree(self.profile, ignore_errors=True)


def _open_page(url, width, height):
    try:
        return _DevToolsPage(url, width, height)
    except TimeoutError as e:  # as _shot: a browser that cannot draw the page here is a missing tool
        pytest.skip(f"headless {CHROMIUM} did not draw the viewer page through the DevTools protocol: {e}")


def _pixels_at_image_centres(shot, view, H, W, clip):
    """The screenshot at the centre of each image pixel under the view (s, x0, y0); NaN outside ``clip``
    (left, top, width, height: the #view element, which hides the rest of a magnified image)."""
    s, x0, y0 = view
    xs = np.floor(x0 + s * (np.arange(W) + 0.5)).astype(int)
    ys = np.floor(y0 + s * (np.arange(H) + 0.5)).astype(int)
    out = np.full((H, W, 3), np.nan)
    okx = (xs >= max(0, clip[0])) & (xs < min(shot.shape[1], clip[0] + clip[2]))
    oky = (ys >= max(0, clip[1])) & (ys < min(shot.shape[0], clip[1] + clip[3]))
    out[np.ix_(oky, okx)] = shot[np.ix_(ys[oky], xs[okx])]
    return out


@needs_chromium
def test_canvas_fills_the_window_and_zoom_pan_keep_the_relit_pixels(tmp_path):
    """At 1280 x 800 the fitted image fills > 80 % of the window in one dimension and shows the library's render
    (sampled at the image pixels' centres); the mouse wheel zooms about the cursor, shift-drag pans, neither
    moves the light nor changes a relit pixel; a plain drag moves the light and the light disc's dot with it;
    Fit brings back the first view, pixel for pixel."""
    res = _result()
    H, W = res.mask.shape
    html = tmp_path / "v.html"
    exposure = write_viewer(html, res)
    m = res.mask.numpy()
    lt = torch.tensor([LIGHTS[0]], dtype=torch.float64)
    lt = lt / lt.norm()
    ref = srgb_encode(np.clip(exposure * res.relight(lt)[0].numpy(), 0, 1))

    def rms(shot_px, inside):
        d = (shot_px - ref)[inside & m]
        return float(np.sqrt((d ** 2).mean()))

    page = _open_page(f"{html.as_uri()}#light={','.join(f'{v:.6f}' for v in lt[0].tolist())}", 1280, 800)
    try:
        rect = page.eval("(r => [r.left, r.top, r.width, r.height])(document.getElementById('c').getBoundingClientRect())")
        assert max(rect[2] / 1280, rect[3] / 800) > 0.8, rect
        assert rect[0] >= 0 and rect[1] >= 0 and rect[0] + rect[2] <= 1280 and rect[1] + rect[3] <= 800, rect
        clip = page.eval("(r => [r.left, r.top, r.width, r.height])(document.getElementById('view').getBoundingClientRect())")
        fit_view = page.view()
        fit_shot = page.screenshot()
        px = _pixels_at_image_centres(fit_shot, fit_view, H, W, clip)
        assert not np.isnan(px).any()
        assert rms(px, True) < 2 / 255, rms(px, True) * 255
        light0 = page.eval("state.light")

        # wheel: zoom in about a point of the image, which stays under the cursor
        s0, x0, y0 = fit_view
        cx, cy = x0 + s0 * 12.3, y0 + s0 * 27.6
        page.mouse("mouseWheel", cx, cy, deltaX=0, deltaY=-400)
        s1, x1, y1 = page.view()
        assert s1 > 1.5 * s0, (s0, s1)
        assert abs((cx - x1) / s1 - 12.3) < 1.5 / s1 and abs((cy - y1) / s1 - 27.6) < 1.5 / s1
        # shift-drag: pan by the drag
        page.drag(640, 400, 540, 460, modifiers=8)
        s2, x2, y2 = page.view()
        assert s2 == s1 and abs(x2 - (x1 - 100)) <= 1 and abs(y2 - (y1 + 60)) <= 1, ((s1, x1, y1), (s2, x2, y2))
        assert page.eval("state.light") == light0  # zoom and pan leave the light alone
        shot = page.screenshot(tmp_path / "zoomed.png")
        px = _pixels_at_image_centres(shot, (s2, x2, y2), H, W, clip)
        vis = ~np.isnan(px[..., 0])
        px[~vis] = 0
        assert (vis & m).sum() > 50
        assert rms(px, vis) < 2 / 255, rms(px, vis) * 255  # the same relit pixels, magnified

        # Fit: the first view again, the same screenshot
        page.eval("document.getElementById('fit').click()")
        assert page.view() == fit_view
        np.testing.assert_array_equal(page.screenshot(), fit_shot)

        # a plain drag on the image moves the light, and the disc's dot shows it (x right, y up)
        page.drag(x0 + s0 * 20, y0 + s0 * 20, x0 + s0 * 30, y0 + s0 * 8)
        light = page.eval("state.light")
        assert light != light0 and light[0] > 0.3 and light[1] > 0.3, light
        dot = page.eval("(d => [+d.getAttribute('cx'), +d.getAttribute('cy')])(document.getElementById('lightdot'))")
        assert dot == pytest.approx([light[0], -light[1]], abs=1e-3)
        # and a click on the disc sets the light
        pad = page.eval("(r => [r.left, r.top, r.width, r.height])(document.getElementById('lightpad').getBoundingClientRect())")
        page.drag(pad[0] + pad[2] / 2, pad[1] + pad[3] / 2, pad[0] + pad[2] / 2, pad[1] + pad[3] / 2, steps=1)
        assert page.eval("state.light") == pytest.approx([0, 0, 1], abs=0.03)

        # the view from the URL: zoom (relative to the fit) and centre (image pixels)
        page.eval("location.hash = 'light=0,0,1&zoom=2&center=10,30'")
        time.sleep(0.3)
        s3, x3, y3 = page.view()
        assert s3 == pytest.approx(2 * s0, rel=1e-5)
        vw, vh = page.eval("document.getElementById('view').dataset.size").split(",")
        left, top = page.eval("(r => [r.left, r.top])(document.getElementById('view').getBoundingClientRect())")
        assert abs(x3 - left - (int(vw) / 2 - s3 * 10)) <= 0.5 and abs(y3 - top - (int(vh) / 2 - s3 * 30)) <= 0.5
    finally:
        page.close()
