"""
Relighting a photometric-stereo result
======================================

The HSH solver fits a BRDF per pixel, so its result renders the object under lights it was never
photographed under (:meth:`torch_hsh.ps.HSHResult.relight`). Here four of the 40 lights of the
small synthetic scene are held out of the fit and the result is relit under them, next to the
held-out photographs, and then under a ring of grazing lights outside the capture's cone. For a
real capture: ``torch-hsh ps CAPTURE --holdout 5 --out results/capture`` reports the held-out
error, and ``torch-hsh view results/capture --out capture.html`` relights it in a browser.
"""
import math

import matplotlib.pyplot as plt
import torch

from torch_hsh import ps
from torch_hsh.render import scenes

# %%
# Fit on 36 lights, keep 4 spread over the grid for the comparison.
scene = scenes.synthetic_scene(48, 40)
images, lights, intensities, mask = scene["images"], scene["lights"], scene["intensities"], scene["mask"]
held = torch.tensor([3, 16, 24, 37])
fit = torch.ones(len(lights), dtype=torch.bool)
fit[held] = False
result = ps.solve_hsh(images[fit], lights[fit], intensities[fit], mask)

# %%
# Relight under the held-out lights (with their intensities) and compare with the photographs.
# The error is relative to the photograph inside the mask; most of it is the sensor noise of the
# photographs, which the display curve lifts to a grey haze in their attached shadows (the relit
# images are exactly 0 there).
relit = result.relight(lights[held], intensities[held])
photos = images[held]
scale = float(torch.quantile(photos[:, mask], 0.99))


def show(x):
    """Linear radiance to a displayable picture (one exposure for every panel, gamma 2.2)."""
    return ((x / scale).clamp(0, 1) ** (1 / 2.2)).numpy()


fig, axes = plt.subplots(2, len(held), figsize=(10, 5.4), layout="constrained")
for j, k in enumerate(held.tolist()):
    rel = float(((relit[j] - photos[j])[mask].norm() / photos[j][mask].norm()))
    axes[0, j].imshow(show(photos[j]))
    axes[0, j].set_title(f"held-out light {k}")
    axes[1, j].imshow(show(relit[j]))
    axes[1, j].set_title(f"relit, rel. error {rel:.3f}")
for ax in axes.flat:
    ax.set_axis_off()
fig.suptitle("photographs (top) and the HSH result relit under the same lights (bottom)")

# %%
# New lights: a ring 70 degrees from the view axis (the capture's lights reach 55 degrees), equal
# white intensities. The highlights move over the glossy regions; the Lambertian part darkens
# towards the side away from the light.
azimuths = [0, 90, 180, 270]
tilt = math.radians(70)
ring = torch.tensor([[math.sin(tilt) * math.cos(math.radians(a)), math.sin(tilt) * math.sin(math.radians(a)),
                      math.cos(tilt)] for a in azimuths], dtype=torch.float64)
new = result.relight(ring)
scale = float(torch.quantile(new[:, mask], 0.995))
fig, axes = plt.subplots(1, len(azimuths), figsize=(10, 2.9), layout="constrained")
for ax, img, a in zip(axes, new, azimuths):
    ax.imshow(show(img))
    ax.set_title(f"light at azimuth {a} deg")
    ax.set_axis_off()
fig.suptitle("relit under new lights, 70 degrees from the view axis")
plt.show()
