"""Analytic BRDF models (differentiable ``torch.nn.Module`` callables).

See :mod:`torch_hsh.brdf.models` for the conventions (local frame, trailing
channel axis, per-pixel parameters by broadcasting, horizon handling).

Example:
    >>> import torch
    >>> from torch_hsh.brdf import get_model
    >>> m = get_model("lambertian", albedo=[0.2, 0.4, 0.6])
    >>> m(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.3, 0.0, 1.0])).shape
    torch.Size([3])
"""
from . import models
from .models import (
    BlinnPhong,
    BRDFModel,
    CookTorranceGGX,
    Lambertian,
    OrenNayar,
    TorranceSparrow,
    WardAnisotropic,
    available_models,
    fresnel_dielectric,
    get_model,
    register_model,
)

__all__ = list(models.__all__)  # the names listed once, in torch_hsh.brdf.models
