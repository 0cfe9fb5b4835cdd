"""Held-out-light evaluation of the HSH solver: fit on a subset of the lights, relighting error on the rest.

It runs the whole solver (:func:`~torch_hsh.ps.solve_hsh`) and the robust
Lambertian baseline, so it sits above the pipeline.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import torch

from .lambertian import robust_lambertian
from .observations import prepare_inputs
from .pipeline import solve_hsh
from .result import HoldoutResult
from .settings import Settings

__all__ = ["HoldoutResult", "holdout_evaluation"]


def holdout_evaluation(
    images: torch.Tensor,
    lights: torch.Tensor,
    intensities: Optional[torch.Tensor] = None,
    mask: Optional[torch.Tensor] = None,
    holdout: int = 10,
    seed: int = 0,
    test_indices: Optional[Sequence[int]] = None,
    *,
    settings: Optional[Settings] = None,
    **overrides,
) -> HoldoutResult:
    """Fit on a subset of the lights and report the relighting error on the rest.

    Args:
        images, lights, intensities, mask: as in :func:`solve_hsh`.
        holdout: number of lights held out (chosen by a seeded permutation).
        seed: permutation seed.
        test_indices: explicit held-out light indices (overrides ``holdout``).
        settings, ``**overrides``: the solver's options, as in :func:`solve_hsh` (e.g. ``order=4``; ``seed``
            here is the permutation's, ``settings.seed`` the solver's).

    Returns:
        :class:`HoldoutResult`. Errors are computed over held-out observations
        inside the mask that are finite and below the detected saturation level.

    Raises:
        ValueError: if fewer than 3 lights would remain for fitting.

    Example:
        >>> ho = holdout_evaluation(images, lights, mask=mask, holdout=5)  # doctest: +SKIP
        >>> ho.relative_rmse < ho.lambertian_relative_rmse  # doctest: +SKIP
        True
    """
    cfg = Settings(**overrides) if settings is None else dataclasses.replace(settings, **overrides)
    d = prepare_inputs(images, lights, intensities, mask, min_lights=4)
    L = d.y.shape[1]
    if test_indices is None:
        if isinstance(holdout, bool) or int(holdout) != holdout or holdout < 1:
            raise ValueError(f"`holdout` must be a positive integer, got {holdout!r}")
        if L - int(holdout) < 3:
            raise ValueError(f"`holdout`={holdout} leaves {L - int(holdout)} lights for fitting; at least 3 are needed")
        g = torch.Generator().manual_seed(int(seed))
        perm = torch.randperm(L, generator=g)
        test = perm[: int(holdout)].sort().values
    else:
        test = torch.as_tensor(list(test_indices), dtype=torch.long).unique()
        if test.numel() < 1 or int(test.min()) < 0 or int(test.max()) >= L:
            raise ValueError(f"`test_indices` must be distinct light indices in [0, {L}), got {list(test_indices)}")
        if L - test.numel() < 3:
            raise ValueError(f"holding out {test.numel()} lights leaves fewer than 3 for fitting")
    keep = torch.ones(L, dtype=torch.bool)
    keep[test] = False
    train = keep.nonzero().squeeze(1)
    dev = images.device
    e_all = None if intensities is None else intensities.to(dev)
    e_tr = None if e_all is None else e_all[train.to(dev)]
    e_te = None if e_all is None else e_all[test.to(dev)]
    res = solve_hsh(images[train.to(dev)], lights[train.to(dev)], e_tr, mask, settings=cfg)
    pred = res.relight(lights[test.to(dev)].to(res.normals.dtype), None if e_te is None else e_te.to(res.normals.dtype))
    obs = images[test.to(dev)].to(pred.dtype)
    m = d.mask.unsqueeze(0).expand(obs.shape[:-1]).unsqueeze(-1).expand_as(obs)
    valid = m & torch.isfinite(obs)
    if "saturation_level" in res.info:
        valid = valid & (obs < 0.99 * res.info["saturation_level"])
    diff = torch.where(valid, pred - obs, torch.zeros_like(obs))
    ref = torch.where(valid, obs, torch.zeros_like(obs))
    nval = valid.sum().clamp(min=1)
    rmse = float(((diff * diff).sum() / nval).sqrt())
    rel = float((diff * diff).sum().sqrt() / (ref * ref).sum().sqrt().clamp(min=1e-30))
    # robust Lambertian baseline on the same split
    lam = robust_lambertian(images[train.to(dev)], lights[train.to(dev)], e_tr, mask)
    lt = torch.nn.functional.normalize(lights[test.to(dev)].to(pred.dtype), dim=-1)
    shade = torch.einsum("...a,la->l...", lam.normals.to(pred.dtype), lt).clamp(min=0.0)
    lpred = lam.albedo.to(pred.dtype).unsqueeze(0) / math.pi * shade.unsqueeze(-1)
    if e_te is not None:
        ee = e_te.to(pred.dtype)
        ee = ee.unsqueeze(-1) if ee.dim() == 1 else ee
        lpred = lpred * ee.reshape(ee.shape[0], *([1] * (lpred.dim() - 2)), ee.shape[-1])
    ldiff = torch.where(valid, lpred - obs, torch.zeros_like(obs))
    lrel = float((ldiff * ldiff).sum().sqrt() / (ref * ref).sum().sqrt().clamp(min=1e-30))
    return HoldoutResult(train, test, rel, rmse, lrel, pred, res)
