"""
Fitted lobes: a BRDF and its Helmholtz fits
===========================================

A GGX and a Blinn-Phong BRDF are projected onto the isotropic Helmholtz basis
(:func:`torch_hsh.project`) at orders 2, 4 and 8, and the fits are evaluated
(:func:`torch_hsh.reconstruct`) in the plane of incidence for light 40 degrees from the normal.
The last panel is the captured energy Acc(P) for every order (:func:`torch_hsh.brdf_accuracy`,
paper Eq. 17). For a measured BRDF run ``torch-hsh fit brdf.binary --order 6 --out fit.npz`` (see
:doc:`/guides/fitting`).
"""
import math

import matplotlib.pyplot as plt
import torch

import torch_hsh
from torch_hsh.brdf import BlinnPhong, CookTorranceGGX

# %%
# Two BRDFs, their parameters positional: a metallic GGX (albedo, specular, roughness, f0) and
# Blinn-Phong (diffuse, specular, shininess). The GGX specular term grows like ``1 / cos`` at grazing angles,
# so its squared integral diverges: it is projected with ``grazing_cutoff`` (the BRDF set to 0
# where a direction is within ``arccos(0.1)`` of the horizon).
brdfs = {
    "GGX, roughness 0.5, f0 1": (CookTorranceGGX(0.3, 0.5, 0.5, 1.0), 0.1),
    "Blinn-Phong, shininess 20": (BlinnPhong(0.5, 0.5, 20.0), None),
}
orders = (2, 4, 8)

# %%
# The plane of incidence: light at ``theta_i = 40`` degrees on the ``-x`` side, view directions
# from ``-90`` to ``90`` degrees through the normal (the mirror direction is at ``+40``). A
# truncated expansion rings and can go below 0; the polar plots clip it at 0.
theta_i = math.radians(40)
angles = torch.linspace(-math.pi / 2, math.pi / 2, 361, dtype=torch.float64)
wo = torch.stack([torch.sin(angles), torch.zeros_like(angles), torch.cos(angles)], -1)
wi = torch.tensor([-math.sin(theta_i), 0.0, math.cos(theta_i)], dtype=torch.float64).expand_as(wo)

fig = plt.figure(figsize=(12, 4.2), layout="constrained")
colours = {2: "tab:blue", 4: "tab:orange", 8: "tab:green"}
accuracy = {}
for i, (name, (brdf, cutoff)) in enumerate(brdfs.items()):
    ax = fig.add_subplot(1, 3, i + 1, projection="polar")
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    ax.set_thetamin(-90)
    ax.set_thetamax(90)
    truth = brdf(wi, wo).reshape(-1).numpy()
    ax.plot(angles.numpy(), truth, "k", lw=2.2, label="BRDF")
    ax.set_rlim(0, 1.1 * float(truth.max()))
    ax.yaxis.set_major_locator(plt.MaxNLocator(3))
    ax.tick_params(axis="y", labelsize=7)
    for order in orders:
        coefficients = torch_hsh.project(brdf, order, grazing_cutoff=cutoff)  # (1, K)
        values = torch_hsh.reconstruct(coefficients, wi, wo, channels=True)[:, 0].clamp(min=0).numpy()
        ax.plot(angles.numpy(), values, color=colours[order], lw=1.4, label=f"order {order}")
    ax.annotate("", xy=(-theta_i, 0.9 * float(truth.max())), xytext=(0, 0),
                arrowprops=dict(arrowstyle="<-", color="0.4"))
    ax.set_title(f"{name}\n(arrow: light, 40 deg)", fontsize=10)
    if i == 0:
        ax.legend(loc="lower left", bbox_to_anchor=(-0.15, -0.15), fontsize=8)
    accuracy[name] = torch_hsh.brdf_accuracy(brdf, max(orders), grazing_cutoff=cutoff).reshape(-1)
    print(name, "Acc(P) at P = 2, 4, 8:", [round(float(accuracy[name][p]), 3) for p in orders])

ax = fig.add_subplot(1, 3, 3)
for name, acc in accuracy.items():
    ax.plot(range(len(acc)), acc.numpy(), "o-", label=name)
ax.set_xlabel("order P")
ax.set_ylabel("Acc(P): fraction of the energy")
ax.set_ylim(0, 1.02)
ax.grid(alpha=0.3)
ax.legend(fontsize=8)
ax.set_title("captured energy Acc(P)", fontsize=10)
plt.show()
