r"""Local shading frames.

World-space light/view directions plus a normal (and optionally a tangent)
become local directions with ``z`` along the normal, the convention of every
basis in :mod:`torch_hsh.kernel`. Everything is batched over leading dimensions
and differentiable.

Conventions:

* :func:`local_frame` returns a rotation matrix ``R`` of shape ``(..., 3, 3)``
  whose **rows** are ``(t, b, n)``: ``R @ v_world = v_local``.
* Without a tangent the frame is built with the branchless construction of
  Duff et al. (2017, "Building an orthonormal basis, revisited"): it is well
  defined for every unit normal, including ``n = (0, 0, ±1)``. An isotropic
  BRDF does not depend on the tangent, so any valid frame gives the same
  values; for anisotropic BRDFs pass the tangent explicitly.
* With a tangent, it is Gram–Schmidt orthogonalised against the normal; if it
  is (nearly) parallel to the normal, the default frame's tangent is used.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from ._checks import broadcast_shapes, check_dirs, check_same

__all__ = ["local_frame", "to_local", "to_world", "isotropic_triple", "reflect"]


def _normalize(v: torch.Tensor) -> torch.Tensor:
    n2 = (v * v).sum(-1, keepdim=True)
    ok = n2 > torch.finfo(v.dtype).tiny * 1e6
    return v * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))


def _default_tangents(n: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    bt = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t, bt


def local_frame(normal: torch.Tensor, tangent: Optional[torch.Tensor] = None) -> torch.Tensor:
    r"""Rotation from world to the local frame of ``normal``.

    Args:
        normal: ``(..., 3)`` surface normals (normalised here).
        tangent: optional ``(..., 3)`` tangents (x axis of the local frame),
            broadcast with ``normal``.

    Returns:
        ``(..., 3, 3)`` matrices with rows ``(t, b, n)`` (right-handed), so that
        ``R @ v`` expresses ``v`` in the local frame.

    Example:
        >>> R = local_frame(torch.tensor([0.0, 0.0, 1.0]))
        >>> torch.allclose(R, torch.eye(3))
        True
    """
    check_dirs(normal, "normal")
    n = _normalize(normal)
    if tangent is None:
        t, b = _default_tangents(n)
    else:
        check_dirs(tangent, "tangent")
        check_same([("normal", normal), ("tangent", tangent)])
        lead = broadcast_shapes([("normal", normal.shape[:-1]), ("tangent", tangent.shape[:-1])])
        n = n.expand(*lead, 3)
        tt = tangent.expand(*lead, 3)
        t_proj = tt - (tt * n).sum(-1, keepdim=True) * n
        t_def, _ = _default_tangents(n)
        ok = (t_proj * t_proj).sum(-1, keepdim=True) > 1e-12 * (tt * tt).sum(-1, keepdim=True).clamp(min=1e-30)
        t = torch.where(ok, _normalize(t_proj), t_def)
        b = torch.cross(n, t, dim=-1)
    return torch.stack([t, b, n], dim=-2)


def to_local(v: torch.Tensor, normal: torch.Tensor, tangent: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Express world directions ``v`` ``(..., 3)`` in the local frame of ``normal`` (and ``tangent``).

    Shapes broadcast over leading dimensions. Returns ``(..., 3)``.

    Example:
        >>> to_local(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 1.0, 0.0]))[2]
        tensor(0.)
    """
    check_dirs(v, "v")
    check_same([("v", v), ("normal", normal)])
    R = local_frame(normal, tangent)
    return (R * v.unsqueeze(-2)).sum(-1)


def to_world(v_local: torch.Tensor, normal: torch.Tensor, tangent: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Inverse of :func:`to_local`: local ``(..., 3)`` to world ``(..., 3)``."""
    check_dirs(v_local, "v_local")
    check_same([("v_local", v_local), ("normal", normal)])
    R = local_frame(normal, tangent)
    return (R * v_local.unsqueeze(-1)).sum(-2)


def isotropic_triple(
    wi: torch.Tensor, wo: torch.Tensor, normal: torch.Tensor
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""The isotropic coordinates :math:`(\cos\theta_i, \cos\theta_o, \cos\Delta\phi)`.

    :math:`\cos\Delta\phi = (\omega_i\cdot\omega_o - \cos\theta_i\cos\theta_o) / (|\omega_{i,t}||\omega_{o,t}|)`
    with tangential parts :math:`\omega_t`. Where either direction is parallel to
    the normal the azimuth is undefined; ``cos_dphi`` is then 1 (any value gives
    the same BRDF value, since every q > 0 basis function vanishes there), and
    its gradient is zero.

    Args:
        wi, wo, normal: ``(..., 3)`` world directions (normalised here), broadcast together.

    Returns:
        Three ``(...)`` tensors.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0])
        >>> isotropic_triple(n, n, n)
        (tensor(1.), tensor(1.), tensor(1.))
    """
    for nm, t in (("wi", wi), ("wo", wo), ("normal", normal)):
        check_dirs(t, nm)
    check_same([("wi", wi), ("wo", wo), ("normal", normal)])
    wi, wo, n = _normalize(wi), _normalize(wo), _normalize(normal)
    ci = (wi * n).sum(-1)
    co = (wo * n).sum(-1)
    dot_t = (wi * wo).sum(-1) - ci * co
    den2 = (1.0 - ci * ci).clamp(min=0) * (1.0 - co * co).clamp(min=0)
    eps = 1e-12 if wi.dtype == torch.float64 else 1e-6
    ok = den2 > eps
    cd = dot_t * torch.rsqrt(torch.where(ok, den2, torch.ones_like(den2)))
    cd = torch.where(ok, cd.clamp(-1.0, 1.0), torch.ones_like(cd))
    return ci, co, cd


def reflect(v: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Mirror direction ``2 (n.v) n - v`` of ``v`` about ``normal``; ``(..., 3)``."""
    check_dirs(v, "v")
    n = _normalize(normal)
    return 2.0 * (v * n).sum(-1, keepdim=True) * n - v
