"""
Photometric stereo on a small synthetic scene
=============================================

A 48 x 48 sphere with three analytic materials (GGX, Blinn-Phong, Torrance-Sparrow) over a
textured albedo, photographed under 40 lights with sensor noise, is solved with the Helmholtz HSH
solver (:func:`torch_hsh.ps.solve_hsh`) and with the robust Lambertian baseline; the angular error
against the true normals shows where the Lambertian model fails on the highlights. On your own
photographs run ``torch-hsh ps path/to/capture --out results/capture`` (see
:doc:`/photometric_stereo`).
"""
import matplotlib.pyplot as plt
import torch

from torch_hsh import ps
from torch_hsh.render import scenes

torch.manual_seed(0)

# %%
# The scene: ``images (L, H, W, 3)``, ``lights (L, 3)``, ``intensities (L, 3)``, ``mask (H, W)``
# and the true ``normals_gt (H, W, 3)``.
scene = scenes.synthetic_scene(48, 40)
images, lights, intensities, mask = scene["images"], scene["lights"], scene["intensities"], scene["mask"]
truth = scene["normals_gt"]
print(scene["name"], tuple(images.shape))

# %%
# Solve: normals and a Helmholtz BRDF per pixel (two basis BRDFs shared by the object, the
# default), and the trimmed Lambertian least squares for comparison.
result = ps.solve_hsh(images, lights, intensities, mask)
lambertian = ps.robust_lambertian(images, lights, intensities, mask)

error_hsh = ps.angular_error(result.normals, truth, mask)
error_lambertian = ps.angular_error(lambertian.normals, truth, mask)
print(f"mean angular error: HSH {error_hsh[mask].mean():.2f} deg, "
      f"robust Lambertian {error_lambertian[mask].mean():.2f} deg "
      f"(order {result.order}, {result.runtime_s:.1f} s)")


# %%
# One of the input images, the estimated normal map (``(n + 1) / 2`` as RGB) and the angular
# error maps of both solvers on the same colour scale.
def show_image(x):
    """Linear radiance to a displayable sRGB-like picture (exposure at the 99th percentile)."""
    return ((x / torch.quantile(x[mask], 0.99)).clamp(0, 1) ** (1 / 2.2)).numpy()


fig, axes = plt.subplots(1, 4, figsize=(12, 3.4), layout="constrained")
axes[0].imshow(show_image(images[len(lights) // 2]))
axes[0].set_title("input (1 of 40 lights)")
axes[1].imshow(((result.normals + 1) / 2 * mask[..., None]).clamp(0, 1).numpy())
axes[1].set_title("HSH normal map")
vmax = float(error_lambertian[mask].quantile(0.98))
for ax, err, name in ((axes[2], error_hsh, "HSH"), (axes[3], error_lambertian, "robust Lambertian")):
    im = ax.imshow(err.numpy(), cmap="magma", vmin=0, vmax=vmax)
    ax.set_title(f"{name}: mean {err[mask].mean():.1f} deg")
fig.colorbar(im, ax=axes[2:], shrink=0.8, label="angular error (deg)")
for ax in axes:
    ax.set_axis_off()
plt.show()
