"""
A Helmholtz BRDF under environment light
========================================

A sphere of one Helmholtz BRDF (a GGX material projected at order 6) rendered under three
built-in procedural skies, a sky gradient over a darker ground with a coloured sun, by
:func:`torch_hsh.render.envmap.render_envmap`: the exact integral of the BRDF against the lighting
expanded to spherical-harmonic order 12, no Monte Carlo. With an HDR map of your own, load it with
``EnvironmentMap.from_exr("sky.exr")``; ``python examples/inverse_envmap.py --synthetic`` fits a
BRDF back from such renders (see :doc:`/environment_lighting`).
"""
import math

import matplotlib.pyplot as plt
import torch

import torch_hsh
from torch_hsh.brdf import CookTorranceGGX
from torch_hsh.render.envmap import procedural_sky, render_envmap

DT = torch.float64


# %%
# A procedural sky in the world frame of the maps (``y`` up): brighter towards the zenith, a
# darker ground and a sun lobe ``exp(40 (d . s - 1))``, 32 x 64 texels (the maps of
# ``examples/inverse_envmap.py --synthetic`` with a 10 times brighter sun).
def sky(sun, sun_rgb, sky_rgb, ground_rgb, height=32):
    return procedural_sky(sun, [0.5 * c for c in sun_rgb], sky_rgb, ground_rgb, height=height, dtype=DT)


skies = {
    "sun high, behind the camera": sky((0.0, 0.9, 0.44), (20.0, 20.0, 22.0), (0.40, 0.50, 0.70), (0.30, 0.30, 0.28)),
    "sun right": sky((0.5, 0.6, 0.62), (30.0, 24.0, 16.0), (0.30, 0.45, 0.80), (0.25, 0.20, 0.15)),
    "low sun, left": sky((-0.7, 0.3, 0.65), (40.0, 20.0, 8.0), (0.50, 0.40, 0.45), (0.20, 0.18, 0.15)),
}

# %%
# Two materials, each one shared set of coefficients ``(1, K)`` (one channel: the colour comes
# from the sky): a glossy GGX projected at order 6 and a Lambertian (exact at order 0, padded).
glossy = torch_hsh.project(CookTorranceGGX(0.3, 0.6, 0.5, 0.5), 6, grazing_cutoff=0.1)  # (1, 84)
matte = torch.zeros_like(glossy)
matte[:, 0] = 2 * 0.6  # the constant function of the basis: a Lambertian of albedo 0.6
materials = {"glossy GGX, order 6": glossy, "Lambertian": matte}

# %%
# The sphere seen along ``-z`` (orthographic), 64 x 64 pixels.
size = 64
u = (torch.arange(size, dtype=DT) + 0.5) / size * 2 - 1
yy, xx = torch.meshgrid(-u, u, indexing="ij")
inside = xx ** 2 + yy ** 2 < 1
normals = torch.stack([xx, yy, torch.sqrt((1 - xx ** 2 - yy ** 2).clamp(min=0))], -1)[inside]

renders = {(label, name): render_envmap(normals, coefficients, env, light_order=12).clamp(min=0)  # (P, 3)
           for name, env in skies.items() for label, coefficients in materials.items()}
exposure = 1 / float(torch.quantile(torch.cat(list(renders.values())), 0.995))

fig, axes = plt.subplots(1 + len(materials), len(skies), figsize=(9, 7.6), layout="constrained",
                         height_ratios=[0.5] + [1] * len(materials))
for j, (name, env) in enumerate(skies.items()):
    axes[0, j].imshow(((env.data / 8).clamp(0, 1) ** (1 / 2.2)).numpy())
    axes[0, j].set_title(name, fontsize=10)
    for i, (label, coefficients) in enumerate(materials.items()):
        image = torch.zeros(size, size, 3, dtype=DT)
        image[inside] = renders[label, name]
        axes[i + 1, j].imshow(((exposure * image).clamp(0, 1) ** (1 / 2.2)).numpy())
        if j == 0:
            axes[i + 1, j].set_ylabel(label)
for ax in axes.flat:
    ax.set_xticks([])
    ax.set_yticks([])
axes[0, 0].set_ylabel("map (equirect.)")
fig.suptitle(f"render_envmap, lighting to SH order 12 ({math.prod(normals.shape[:1])} pixels per sphere)")
plt.show()
