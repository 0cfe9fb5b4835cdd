"""
The relighting viewer in the browser
====================================

``torch-hsh view`` writes a photometric-stereo result as one self-contained HTML page that relights
it with WebGL2 as you drag the light over the image (buttons switch to the normals, albedo,
confidence and residual). Here the small demo scene is solved with ``torch-hsh demo``, the page is
written with ``torch-hsh view`` and photographed in headless Chromium at two light directions and in
the normals mode. Where no Chromium is installed (or it cannot draw WebGL2) the picture is the
screenshot committed with the documentation instead. On your own result:
``torch-hsh view results/cat --out cat.html`` and open ``cat.html`` (see :doc:`/rti`).
"""
import shutil
import subprocess
import tempfile
from pathlib import Path

import matplotlib.image as mpimg
import matplotlib.pyplot as plt

from torch_hsh.cli import run

# sphinx_gallery_thumbnail_number = 2
SCALE = 4  # device pixels per CSS pixel of the screenshots: the 48 x 48 canvas becomes 192 x 192
SIZE = 48
SHOTS = {"light from the upper left": "light=-0.5,0.5,0.707&mode=relit",
         "light from the right": "light=0.8,-0.1,0.59&mode=relit",
         "normals mode": "light=0,0,1&mode=normals"}

# %%
# The result folder and the page, with the commands as you would type them.
work = Path(tempfile.mkdtemp(prefix="torch_hsh_gallery_"))
run(["demo", "--scene", "small", "--size", str(SIZE), "--out", str(work / "small"), "--quiet"])
run(["view", str(work / "small"), "--out", str(work / "small.html"), "--quiet"])
print(f"torch-hsh view wrote a page of {(work / 'small.html').stat().st_size / 2 ** 10:.0f} KiB")


# %%
# Screenshots: Chromium in headless mode with SwiftShader's WebGL2 (no GPU needed); the page reads
# the light and the mode from its URL (``#light=x,y,z&mode=relit``). Any failure (no Chromium, a
# time-out, a page that drew nothing) falls back to the committed picture.
def screenshot(chromium, html, fragment, out, width=520, height=110, timeout=30):
    cmd = [chromium, "--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
           f"--force-device-scale-factor={SCALE}", "--hide-scrollbars", f"--window-size={width},{height}",
           "--virtual-time-budget=5000", f"--screenshot={out}",
           f"{html.as_uri()}#{fragment}"]
    subprocess.run(cmd, capture_output=True, timeout=timeout, check=True)
    return mpimg.imread(out)[..., :3]  # the whole page, (height, width) x SCALE


chromium = next((shutil.which(c) for c in ("chromium", "chromium-browser", "google-chrome") if shutil.which(c)), None)
pages = {}
if chromium is not None:
    try:
        for k, (title, fragment) in enumerate(SHOTS.items()):
            pages[title] = screenshot(chromium, work / "small.html", fragment, work / f"shot{k}.png")
        half = SIZE * SCALE // 2  # both halves of the canvas drawn (a page caught mid-paint shows only the top)
        if any(min(p[:half, : 2 * half].max(), p[half: 2 * half, : 2 * half].max()) < 0.1 for p in pages.values()):
            raise RuntimeError("the canvas was not drawn (no WebGL2?)")
    except (OSError, subprocess.SubprocessError, RuntimeError) as e:
        print(f"no screenshot from {chromium}: {e}")
        pages = {}
else:
    print("no Chromium on the PATH: showing the committed screenshot")

if pages:
    first = next(iter(pages.values()))
    fig = plt.figure(figsize=(first.shape[1] / 200, first.shape[0] / 200), layout="constrained")
    plt.imshow(first)
    plt.axis("off")
    plt.title("the page of torch-hsh view (headless Chromium)", fontsize=9)
    fig, axes = plt.subplots(1, len(pages), figsize=(9, 3.3), layout="constrained")
    for ax, (title, page) in zip(axes, pages.items()):
        ax.imshow(page[: SIZE * SCALE, : SIZE * SCALE])
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
else:
    # docs/images/rti_viewer.png: three relit views and the normals of a real capture
    # sphinx-gallery runs the script without __file__: look upward from the working folder too
    here = Path(globals().get("__file__", Path.cwd() / "plot_viewer.py")).resolve()
    committed = next((d / "docs" / "images" / "rti_viewer.png" for d in [*here.parents, *Path.cwd().resolve().parents,
                      Path.cwd().resolve()] if (d / "docs" / "images" / "rti_viewer.png").exists()),
                     here.parents[2] / "docs" / "images" / "rti_viewer.png")
    picture = committed if committed.exists() else work / "small" / "relighting.png"
    fig = plt.figure(figsize=(9, 3), layout="constrained")
    plt.imshow(mpimg.imread(picture))
    plt.axis("off")
    plt.title("the viewer (committed screenshot; no headless Chromium here)" if committed.exists()
              else "the relighting that torch-hsh demo wrote (no headless Chromium here)", fontsize=10)
shutil.rmtree(work, ignore_errors=True)
plt.show()
