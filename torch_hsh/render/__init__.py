r"""Rendering: images of Helmholtz or analytic BRDFs under point lights and environment maps.

Modules::

    torch_hsh.render.images      point-light image formation (render, render_coefficients, render_model,
                                 shading_basis, brdf_cosine, sensor noise and quantisation)
    torch_hsh.render.envmap      environment lighting (EnvironmentMap, render_envmap, EnvironmentLighting)
    torch_hsh.render.scenes      synthetic photometric-stereo scenes (geometry, materials, lights, demo_scene)
    torch_hsh.render.visibility  cast shadows of a height field by ray marching (cast_shadow_mask)

Frame: the DiLiGenT camera frame (x right, y up, z toward the camera), an orthographic view
along ``-z``; lights ``(L, 3)`` point toward the lights; images are ``(L, *S, C)``.

Example:
    >>> import torch
    >>> from torch_hsh.render import render, scenes
    >>> normals, mask = scenes.sphere_normals(16)
    >>> lights = scenes.diligent_like_lights(4, seed=0)
    >>> albedo = torch.full((16, 16, 3), 0.5)
    >>> from torch_hsh.brdf import Lambertian
    >>> render(normals, lights, Lambertian(albedo)).shape
    torch.Size([4, 16, 16, 3])
"""
from . import envmap, images, scenes, visibility
from .envmap import *  # noqa: F401,F403
from .images import *  # noqa: F401,F403
from .visibility import cast_shadow_mask

__all__ = ["envmap", "images", "scenes", "visibility", "cast_shadow_mask", *images.__all__, *envmap.__all__]
