r"""Differentiable, batched image formation for photometric stereo.

Image formation (math notes, section 7): an orthographic camera looks down
``-z``, so the view direction toward the camera is ``v = (0, 0, 1)`` for every
pixel; lights are distant, with direction ``l_j`` (unit, world frame) and RGB
intensity ``e_j``; each pixel has a unit normal ``n`` and its own BRDF ``f``:

.. math::
    I_{jc} = e_{jc}\, f_c(l_j', v')\, \max(0, n \cdot l_j)\; V_j,

where ``'`` marks the local frame of ``n`` and ``V_j`` is an optional
visibility (cast-shadow) mask; ``render(..., ambient=a)`` replaces it by
``V_j + a (1 - V_j)`` so that cast shadows stay dim instead of black (a crude
interreflection / room-light term, off by default). Attached shadows (``n . l <= 0``) are always
applied; the isotropic basis itself is zero there too.

A BRDF is either

* a tensor of **coefficient maps** in the isotropic Helmholtz basis
  (:func:`torch_hsh.helmholtz_isotropic_world`), shape ``(*S, C, K)`` with
  ``S`` the pixel shape (``(H, W)`` or ``(N,)``) and ``K = (P+1)(P+2)(P+3)/6``
  (the order is inferred from ``K``), or
* a **callable** ``f(wi, wo) -> (..., C)`` taking local directions (for
  example an analytic model of :mod:`torch_hsh.brdf` with per-pixel
  parameters of shape ``(*S, C)``); it is called with ``wi`` of shape
  ``(L, *S, 3)`` and ``wo`` of shape ``(L, *S, 3)``.

Sensor effects (all optional, applied in this order by :func:`render`):
Gaussian read noise plus signal-dependent shot noise (seeded), saturation
clipping and quantisation to ``bits`` bits. Noise is additive, hence
differentiable; clipping has zero gradient beyond the clip level and
quantisation uses a straight-through estimator (gradient of the identity).

Shapes everywhere: lights ``(L, 3)``; intensities ``None`` (all ones),
``(L,)`` or ``(L, C)``; images ``(L, *S, C)``.
"""
from __future__ import annotations

from typing import Callable, Optional, Union

import torch

from .._checks import check_dirs, check_order, check_same, check_shape, check_tensor
from ..kernel import helmholtz_isotropic_world, num_isotropic
from ..frames import local_frame

__all__ = [
    "VIEW",
    "view_direction",
    "shading_basis",
    "render",
    "render_coefficients",
    "render_model",
    "brdf_cosine",
    "add_sensor_noise",
    "quantize",
    "order_from_num_functions",
]

#: Direction toward the orthographic camera in the DiLiGenT frame (x right, y up, z toward the camera).
VIEW = (0.0, 0.0, 1.0)


def view_direction(like: torch.Tensor) -> torch.Tensor:
    """The view direction ``(0, 0, 1)`` as a ``(3,)`` tensor with ``like``'s dtype and device.

    Example:
        >>> view_direction(torch.zeros(2, dtype=torch.float64))
        tensor([0., 0., 1.], dtype=torch.float64)
    """
    return torch.tensor(VIEW, dtype=like.dtype, device=like.device)


def order_from_num_functions(k: int) -> int:
    """Order ``P`` with ``num_isotropic(P) == k``; ``ValueError`` if there is none.

    Example:
        >>> order_from_num_functions(20)
        3
    """
    for p in range(0, 41):
        n = num_isotropic(p)
        if n == k:
            return p
        if n > k:
            break
    raise ValueError(
        f"the last axis of the coefficient maps has {k} entries, which is not the size of an isotropic "
        "Helmholtz basis (1, 4, 10, 20, 35, 56, ... = (P+1)(P+2)(P+3)/6)"
    )


def _check_lights(lights: torch.Tensor, name: str = "lights") -> torch.Tensor:
    check_dirs(lights, name)
    check_shape(lights, name, ("L", 3))
    if lights.shape[0] < 1:
        raise ValueError(f"`{name}` must hold at least one light, got shape {tuple(lights.shape)}")
    return lights


def _intensities(intensities, L: int, C: int, like: torch.Tensor) -> torch.Tensor:
    """Return ``(L, C)`` intensities on ``like``'s device/dtype."""
    if intensities is None:
        return torch.ones(L, C, dtype=like.dtype, device=like.device)
    check_tensor(intensities, "intensities")
    check_shape(intensities, "intensities", ("L",), ("L", 1), ("L", "C"), sizes={"L": L, "C": C})
    if intensities.dim() == 1:
        intensities = intensities.unsqueeze(-1)
    return intensities.to(like.dtype).expand(L, C)


def _lit(img: torch.Tensor, intensities) -> torch.Tensor:
    """``(L, *S, C)`` images of unit-intensity lights times the light ``intensities`` (see :func:`_intensities`)."""
    e = _intensities(intensities, img.shape[0], img.shape[-1], img)
    return img * e.reshape(e.shape[0], *([1] * (img.dim() - 2)), e.shape[1])


def shading_basis(
    normals: torch.Tensor,
    lights: torch.Tensor,
    order: int,
    view: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    r"""Design matrix of the linear image model: :math:`B_k(l_j, v, n) \max(0, n\cdot l_j)`.

    With coefficients ``a`` of shape ``(*S, C, K)`` the rendered image is
    ``I[j, ..., c] = e[j, c] * sum_k a[..., c, k] * shading_basis(...)[j, ..., k]``.

    Args:
        normals: ``(*S, 3)`` normals (normalised here), world frame.
        lights: ``(L, 3)`` light directions toward the light, world frame.
        order: basis order ``P``.
        view: optional ``(3,)`` or ``(*S, 3)`` direction toward the camera;
            default ``(0, 0, 1)``.

    Returns:
        ``(L, *S, K)``; zero where ``n . l <= 0`` or ``n . v < 0``. Differentiable
        with respect to ``normals`` and ``lights``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> shading_basis(n, torch.tensor([[0.0, 0.6, 0.8]]), 2).shape
        torch.Size([1, 1, 10])
    """
    check_dirs(normals, "normals")
    _check_lights(lights)
    check_same([("normals", normals), ("lights", lights)])
    order = check_order(order)
    S = normals.shape[:-1]
    if view is None:
        view = view_direction(normals)
    else:
        check_dirs(view, "view")
        check_same([("normals", normals), ("view", view)])
    nrm = torch.nn.functional.normalize(normals, dim=-1)
    L = lights.shape[0]
    li = lights.reshape(L, *([1] * len(S)), 3)
    B = helmholtz_isotropic_world(li, view, nrm, order)  # (L, *S, K)
    cos = (nrm * li).sum(-1).clamp(min=0.0)
    return B * cos.unsqueeze(-1)


def render_coefficients(
    normals: torch.Tensor,
    lights: torch.Tensor,
    coefficients: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    view: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """Noise-free rendering of per-pixel isotropic Helmholtz coefficient maps.

    :func:`render_model` with the BRDF given as ``coefficients``, ``(*S, C, K)`` (the order is inferred
    from ``K``); ``normals``, ``lights``, ``intensities`` and ``view`` as there.

    Returns:
        ``(L, *S, C)`` radiance (not clamped: a fitted expansion may be negative).

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> a = torch.zeros(1, 3, 4); a[..., 0] = 2.0  # Lambertian, albedo 1
        >>> render_coefficients(n, torch.tensor([[0.0, 0.0, 1.0]]), a)[0, 0]  # 1/pi
        tensor([0.3183, 0.3183, 0.3183])
    """
    check_tensor(coefficients, "coefficients", min_dims=2)
    return _lit(brdf_cosine(normals, lights, coefficients, view), intensities)


def _check_coefficient_maps(normals: torch.Tensor, coefficients: torch.Tensor) -> int:
    """Shape/dtype checks of ``(*S, C, K)`` coefficient maps against ``normals``; returns the order."""
    check_tensor(coefficients, "coefficients", min_dims=2)
    check_dirs(normals, "normals")
    S = normals.shape[:-1]
    if coefficients.shape[:-2] != S:
        raise ValueError(
            f"`coefficients` must have shape (*S, C, K) with S = {tuple(S)} (the pixel shape of `normals`), "
            f"got {tuple(coefficients.shape)}"
        )
    check_same([("normals", normals), ("coefficients", coefficients)])
    return order_from_num_functions(coefficients.shape[-1])


def brdf_cosine(
    normals: torch.Tensor,
    dirs: torch.Tensor,
    brdf: Union[torch.Tensor, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]],
    view: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    r"""BRDF times cosine, :math:`f(l', v') \max(0, n\cdot l)`, for every incident direction and pixel.

    The BRDF-evaluation piece shared by the point-light renderer and the
    environment-map reference (:func:`torch_hsh.render.envmap.render_envmap_reference`).

    Args:
        normals: ``(*S, 3)``.
        dirs: ``(L, 3)`` incident directions (toward the light), world frame.
        brdf: coefficient maps ``(*S, C, K)`` (isotropic Helmholtz; not clamped) or a
            callable ``f(wi, wo) -> (L, *S, C)`` on local directions.
        view: optional direction toward the camera (default ``(0, 0, 1)``).

    Returns:
        ``(L, *S, C)``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> a = torch.zeros(1, 1, 4); a[..., 0] = 2.0
        >>> brdf_cosine(n, torch.tensor([[0.0, 0.6, 0.8]]), a)  # 0.8 / pi
        tensor([[[0.2546]]])
    """
    if isinstance(brdf, torch.Tensor):
        order = _check_coefficient_maps(normals, brdf)
        Phi = shading_basis(normals, dirs, order, view)  # (L, *S, K)
        return torch.einsum("l...k,...ck->l...c", Phi, brdf)
    if callable(brdf):
        return _model_cosine(normals, dirs, brdf, view)
    raise TypeError(
        f"`brdf` must be coefficient maps (a tensor of shape (*S, C, K)) or a callable f(wi, wo), "
        f"got {type(brdf).__name__}"
    )


def render_model(
    normals: torch.Tensor,
    lights: torch.Tensor,
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    intensities: Optional[torch.Tensor] = None,
    view: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """Noise-free rendering of a BRDF callable with per-pixel parameters.

    Args:
        normals: ``(*S, 3)``.
        lights: ``(L, 3)``.
        model: ``f(wi, wo) -> (L, *S, C)`` with local directions ``(L, *S, 3)``
            (z = normal); e.g. ``torch_hsh.brdf.CookTorranceGGX(albedo, ...)``
            with parameters of shape ``(*S, C)``.
        intensities: ``None``, ``(L,)`` or ``(L, C)``.
        view: optional direction toward the camera (default ``(0, 0, 1)``).

    Returns:
        ``(L, *S, C)`` radiance ``e f max(0, n.l)``.

    Example:
        >>> lam = lambda wi, wo: torch.full(wi.shape[:-1] + (3,), 1 / torch.pi)
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> render_model(n, torch.tensor([[0.0, 0.0, 1.0]]), lam)[0, 0]
        tensor([0.3183, 0.3183, 0.3183])
    """
    return _lit(_model_cosine(normals, lights, model, view), intensities)


def _model_cosine(normals, lights, model, view) -> torch.Tensor:
    """:func:`brdf_cosine` of a BRDF callable: ``(L, *S, C)``, zero below either horizon."""
    check_dirs(normals, "normals")
    _check_lights(lights)
    check_same([("normals", normals), ("lights", lights)])
    if not callable(model):
        raise TypeError(f"`model` must be callable f(wi, wo) -> (..., C), got {type(model).__name__}")
    S = normals.shape[:-1]
    L = lights.shape[0]
    if view is None:
        view = view_direction(normals)
    R = local_frame(normals)  # (*S, 3, 3), rows t, b, n
    wi = torch.einsum("...ab,lb->l...a", R, lights)  # (L, *S, 3)
    wo = torch.einsum("...ab,...b->...a", R, view.expand(*S, 3))
    wo = wo.unsqueeze(0).expand(L, *S, 3)
    f = model(wi, wo)
    if not isinstance(f, torch.Tensor) or f.shape[: 1 + len(S)] != (L, *S) or f.dim() != len(S) + 2:
        got = tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__
        raise ValueError(f"`model(wi, wo)` must return shape (L, *S, C) = ({L}, {', '.join(map(str, S))}, C), got {got}")
    cos = wi[..., 2].clamp(min=0.0)
    up = (wo[..., 2] >= 0) & (wi[..., 2] > 0)
    return torch.where(up.unsqueeze(-1), f * cos.unsqueeze(-1), torch.zeros_like(f))


def add_sensor_noise(
    images: torch.Tensor,
    read_std: float = 0.0,
    shot_gain: float = 0.0,
    seed: Optional[int] = None,
) -> torch.Tensor:
    r"""Gaussian read noise plus (Gaussian-approximated) shot noise, seeded.

    ``out = I + sqrt(read_std**2 + shot_gain * max(I, 0)) * N(0, 1)``: the
    variance of shot noise grows linearly with the signal (Poisson with
    ``1 / shot_gain`` photo-electrons per unit of radiance).

    Args:
        images: any shape.
        read_std: standard deviation of the signal-independent noise (>= 0).
        shot_gain: variance per unit signal (>= 0).
        seed: seed of a private generator on ``images.device`` (``None``:
            the global generator).

    Returns:
        Noisy images, same shape; differentiable with respect to ``images``.

    Example:
        >>> x = torch.ones(4)
        >>> torch.equal(add_sensor_noise(x, 0.1, seed=1), add_sensor_noise(x, 0.1, seed=1))
        True
    """
    check_tensor(images, "images")
    if read_std < 0 or shot_gain < 0:
        raise ValueError(f"`read_std` and `shot_gain` must be >= 0, got {read_std} and {shot_gain}")
    if read_std == 0 and shot_gain == 0:
        return images
    gen = None
    if seed is not None:
        gen = torch.Generator(device=images.device)
        gen.manual_seed(int(seed))
    z = torch.randn(images.shape, generator=gen, dtype=images.dtype, device=images.device)
    var = read_std ** 2 + shot_gain * images.clamp(min=0.0)
    return images + torch.sqrt(var) * z


def quantize(images: torch.Tensor, bits: int = 16, max_value: float = 1.0) -> torch.Tensor:
    """Clip to ``[0, max_value]`` and round to the ``2**bits`` codes ``0 .. 2**bits - 1`` (straight-through gradient).

    Code ``k`` stands for ``k * max_value / (2**bits - 1)``; halfway values round
    to the even code (``torch.round``).

    Args:
        images: any shape.
        bits: 1..32.
        max_value: the value mapped to the largest code (the saturation level).

    Returns:
        Quantised images in the same units as the input.

    Example:
        >>> quantize(torch.tensor([0.5, 2.0]), bits=1)  # 0.5 is halfway: even code 0; 2.0 saturates
        tensor([0., 1.])
        >>> quantize(torch.tensor([0.3, 0.7]), bits=2)  # codes 1 and 2 of 0..3
        tensor([0.3333, 0.6667])
    """
    check_tensor(images, "images")
    if isinstance(bits, bool) or int(bits) != bits or not 1 <= bits <= 32:
        raise ValueError(f"`bits` must be an integer in [1, 32], got {bits!r}")
    if not max_value > 0:
        raise ValueError(f"`max_value` must be > 0, got {max_value}")
    levels = float(2 ** int(bits) - 1)
    x = images.clamp(0.0, max_value)
    q = torch.round(x / max_value * levels) * (max_value / levels)
    return x + (q - x).detach()


def render(
    normals: torch.Tensor,
    lights: torch.Tensor,
    brdf: Union[torch.Tensor, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]],
    intensities: Optional[torch.Tensor] = None,
    visibility: Optional[torch.Tensor] = None,
    view: Optional[torch.Tensor] = None,
    read_std: float = 0.0,
    shot_gain: float = 0.0,
    seed: Optional[int] = None,
    saturation: Optional[float] = None,
    bits: Optional[int] = None,
    mask: Optional[torch.Tensor] = None,
    ambient: float = 0.0,
) -> torch.Tensor:
    r"""Render photometric-stereo images (section 7 of the math notes).

    Args:
        normals: ``(*S, 3)`` per-pixel normals, world frame (DiLiGenT frame:
            x right, y up, z toward the camera); ``S`` is ``(H, W)`` or ``(N,)``.
        lights: ``(L, 3)`` unit directions toward the lights.
        brdf: coefficient maps ``(*S, C, K)`` in the isotropic Helmholtz basis,
            or a callable ``f(wi, wo) -> (L, *S, C)`` on local directions
            (an analytic model of :mod:`torch_hsh.brdf` with per-pixel parameters).
        intensities: ``None`` (ones), ``(L,)`` or ``(L, C)`` light intensities.
        visibility: optional ``(L, *S)`` cast-shadow mask (bool or float in [0, 1]).
        view: optional direction toward the camera (default ``(0, 0, 1)``).
        read_std: std of the additive Gaussian read noise (as in
            :func:`add_sensor_noise`).
        shot_gain: variance per unit signal of the shot noise (as in
            :func:`add_sensor_noise`).
        seed: noise seed (reproducible results).
        saturation: clip radiance at this level (also the full-scale value for
            quantisation); ``None``: no clipping (quantisation then uses the
            maximum of the rendered images as full scale).
        bits: quantise to this many bits (e.g. 16), after clipping.
        mask: optional ``(*S)`` bool; pixels outside are set to zero.
        ambient: fraction in ``[0, 1]`` of the unoccluded radiance that still
            reaches cast-shadowed observations (a crude stand-in for
            interreflections and room light: a real cast shadow is dim, not
            black). The visibility factor becomes ``V + ambient (1 - V)``,
            applied before the noise; attached shadows (``n . l <= 0``) stay
            zero. No effect without ``visibility``; ``0`` (default) leaves the
            images unchanged.

    Returns:
        ``(L, *S, C)`` images. Negative radiance from a coefficient expansion is
        clamped to zero (a camera cannot measure it); the clamp is applied
        before the noise.

    Example:
        >>> n = torch.nn.functional.normalize(torch.randn(5, 3).abs(), dim=-1)
        >>> a = torch.zeros(5, 3, 10); a[..., 0] = 1.0
        >>> render(n, torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]), a, read_std=0.01, seed=0).shape
        torch.Size([2, 5, 3])
    """
    check_dirs(normals, "normals")
    lights = _check_lights(lights)
    check_same([("normals", normals), ("lights", lights)])
    if isinstance(brdf, torch.Tensor):
        img = render_coefficients(normals, lights, brdf, intensities, view).clamp(min=0.0)
    elif callable(brdf):
        img = render_model(normals, lights, brdf, intensities, view)
    else:
        raise TypeError(
            f"`brdf` must be coefficient maps (a tensor of shape (*S, C, K)) or a callable f(wi, wo), "
            f"got {type(brdf).__name__}"
        )
    S = normals.shape[:-1]
    if isinstance(ambient, bool) or not isinstance(ambient, (int, float)) or not 0 <= ambient <= 1:
        raise ValueError(f"`ambient` must be a number in [0, 1], got {ambient!r}")
    if visibility is not None:
        if not isinstance(visibility, torch.Tensor):
            raise TypeError(f"`visibility` must be a torch.Tensor, got {type(visibility).__name__}")
        if tuple(visibility.shape) != (lights.shape[0], *S):
            raise ValueError(
                f"`visibility` must have shape (L, *S) = {(lights.shape[0], *S)}, got {tuple(visibility.shape)}"
            )
        vis = visibility.to(img.dtype)
        if ambient:
            vis = vis + ambient * (1 - vis)
        img = img * vis.unsqueeze(-1)
    img = add_sensor_noise(img, read_std, shot_gain, seed)
    if saturation is not None:
        if not saturation > 0:
            raise ValueError(f"`saturation` must be > 0, got {saturation}")
    if bits is not None:
        full = float(saturation) if saturation is not None else float(img.detach().max().clamp(min=1e-30))
        img = quantize(img, bits, full)
    elif saturation is not None:
        img = img.clamp(max=float(saturation))
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or tuple(mask.shape) != tuple(S):
            raise ValueError(f"`mask` must be a tensor of shape {tuple(S)}, got {getattr(mask, 'shape', mask)!r}")
        img = img * mask.to(img.dtype).unsqueeze(-1)
    return img
