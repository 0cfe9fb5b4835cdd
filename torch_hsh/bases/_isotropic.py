r"""Shared pieces of the isotropic comparison bases (Westin, Gautron, Koenderink--van Doorn).

Every isotropic basis here is a sum of products

.. math:: c_k\,T_{a_k}(\theta_i)\,T_{b_k}(\theta_o)\,A_{z_k}(\Delta\phi)

of per-direction polar tables ``T`` and an azimuthal table ``A`` of
:math:`\rho_i^q\rho_o^q\{\cos,\sin\}(q\Delta\phi)`-type columns built from the complex number
:math:`c = (x_i - i y_i)(x_o + i y_o)` (:math:`|c| = \sin\theta_i\sin\theta_o`,
:math:`\arg c = \phi_o - \phi_i`). :func:`pair_frame` does the validation, broadcasting,
normalisation and horizon mask that every ``evaluate`` starts with, and
:func:`gather_rows` the gather-multiply that every one ends with (symmetrised or not).
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from ..kernel import _const
from ._products import broadcast_pair, complex_powers, unit_dirs

__all__ = ["pair_frame", "azimuth_table", "gather_rows"]


def pair_frame(wi: torch.Tensor, wo: torch.Tensor, hemisphere: bool = True):
    """Validate and flatten a direction pair.

    Returns:
        ``lead, zi, zo, cr, ci, valid``: the broadcast leading shape, the cosines, the
        real and imaginary parts of ``c`` (all ``(N,)``) and the validity mask
        (non-zero vectors, and ``z >= 0`` for both when ``hemisphere``).
    """
    lead, wi, wo = broadcast_pair(wi, wo)
    xi, yi, zi, oki = unit_dirs(wi)
    xo, yo, zo, oko = unit_dirs(wo)
    valid = oki & oko
    if hemisphere:
        valid = valid & (zi >= 0) & (zo >= 0)
    return lead, zi, zo, xi * xo + yi * yo, xi * yo - yi * xo, valid


def azimuth_table(cr: torch.Tensor, ci: torch.Tensor, valid: torch.Tensor, order: int, sines: bool,
                  scale: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[Re (s c)^q, q = 0..P] (+ [Im (s c)^q, q = 1..P] if sines)``, zero where not ``valid``."""
    if scale is not None:
        cr, ci = cr * scale, ci * scale
    RE, IM = complex_powers(cr, ci, order)
    A = torch.cat([RE, IM], -1) if sines else RE
    return A * valid.to(cr.dtype).unsqueeze(-1)


def gather_rows(Ti: torch.Tensor, To: torch.Tensor, A: torch.Tensor, ia: Sequence[int], ib: Sequence[int],
                iz: Sequence[int], coef: Sequence[float], key: tuple, symmetric: bool, lead) -> torch.Tensor:
    """``coef * (Ti[ia] To[ib] (+ Ti[ib] To[ia] if symmetric)) * A[iz]``, reshaped to ``(*lead, K)``."""
    dev, dt = Ti.device, Ti.dtype
    ta = _const(key + ("a",), list(ia), dev, None)
    tb = _const(key + ("b",), list(ib), dev, None)
    tz = _const(key + ("z",), list(iz), dev, None)
    out = Ti.index_select(-1, ta) * To.index_select(-1, tb)
    if symmetric:
        out = out.addcmul(Ti.index_select(-1, tb), To.index_select(-1, ta))
    out = out * A.index_select(-1, tz) * _const(key + ("c",), list(coef), dev, dt)
    return out.reshape(*lead, out.shape[-1])
