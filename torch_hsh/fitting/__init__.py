r"""Projection, least-squares fitting, reconstruction and energy analysis.

Modules: :mod:`~torch_hsh.fitting.projection` (:func:`project`, :func:`brdf_energy`,
:func:`brdf_accuracy`), :mod:`~torch_hsh.fitting.rules` (the product rules) and
:mod:`~torch_hsh.fitting.convergence` (their refinement), :mod:`~torch_hsh.fitting.least_squares`
(:func:`fit`), :mod:`~torch_hsh.fitting.coefficients` (:func:`reconstruct`, :func:`truncate`,
:func:`energy_accuracy`), :mod:`~torch_hsh.fitting.normal_exitance` and
:mod:`~torch_hsh.fitting.albedo`; every public name is importable from ``torch_hsh.fitting``.

Every function takes a ``basis`` argument: a registered name (see
:func:`torch_hsh.bases.available_bases`) or a :class:`torch_hsh.bases.Basis`;
the default is ``"helmholtz_isotropic"``. Nothing here is specific to the
Helmholtz bases except :func:`directional_albedo`'s closed form (which falls
back to quadrature for other bases).

Conventions
-----------
* Directions are in the local frame (z = normal). A BRDF is a callable
  ``brdf(wi, wo)`` taking two ``(M, 3)`` tensors and returning ``(M,)`` (one
  channel) or ``(M, C)`` (e.g. RGB).
* Coefficients: ``(K,)`` for one scalar BRDF, ``(C, K)`` for C channels, with
  leading batch dimensions in front where documented.
* Projection (paper Eq. 14): :math:`a_k = \int_{\Omega_i}\int_{\Omega_o} f\,B_k\,
  d\omega_i\,d\omega_o`. The integral is always taken over the **upper**
  hemispheres: for ``domain == "sphere"`` bases (orthonormal over full spheres)
  this is exactly the projection of the BRDF extended by zero below the
  horizon, without integrating across the discontinuity at ``z = 0``.
* Default quadrature sizes: ``n_theta = 2 (P + 1)`` Gauss--Legendre nodes in
  ``cos(theta)`` and ``n_phi = 2 (2P + 1)`` azimuths per direction. The
  product of a basis function of order ``<= P`` with a function band-limited
  to order ``L`` is integrated exactly when ``n_theta >= (L + P)/2 + 1`` and
  ``n_phi >= L + P + 1`` (see :mod:`torch_hsh.quadrature`), so the defaults
  project any function band-limited to order ``L <= 3P + 1`` **exactly** (the
  minimal exact rule for ``L = P`` would be ``P + 1`` and ``2P + 1``; the factor
  two buys accuracy on BRDFs that are not band-limited). Pass larger values for
  sharp specular lobes.
* **Convergence control** (default): when neither ``n_theta`` nor ``n_phi`` is
  given, :func:`project`, :func:`brdf_energy` and :func:`brdf_accuracy` estimate
  their own error by comparing successive rules and refine until the estimate is
  below ``tol`` (see :mod:`torch_hsh.fitting.rules` and :mod:`torch_hsh.fitting.convergence`); when ``max_evaluations`` runs
  out they raise :class:`ConvergenceError` carrying the estimate (``strict=False``:
  a :class:`ConvergenceWarning` and the best result). Passing ``n_theta``/``n_phi``
  (or ``tol=None``) selects one fixed rule without an estimate, as before.
  ``grazing_cutoff=c`` integrates over :math:`\cos\theta_i, \cos\theta_o \ge c`
  only; it is **required** where the integral diverges, e.g. :math:`\iint f^2` of
  the GGX, Ward, Oren--Nayar and Torrance--Sparrow models (they grow like
  :math:`1/\cos` at grazing angles), which the refinement detects and reports.
  Cost: sharp lobes need many azimuths (the azimuthal width of a specular lobe
  shrinks towards the grazing mirror configuration; ``n_phi`` of 1000-4000 for GGX
  roughness 0.3), which the azimuthal low-pass keeps cheap (seconds). A BRDF with
  an integrable grazing singularity (raw GGX: :math:`\int f B` is finite) converges
  only algebraically in ``n_theta`` (about 30 s at P = 8 for raw GGX roughness 0.7);
  a ``grazing_cutoff`` makes it fast again (about 1 s).
* Singularities at grazing angles: Gauss--Legendre nodes are strictly inside
  ``(0, 1)``, so ``z = 0`` is never evaluated and integrable singularities
  (e.g. :math:`z^{-1/2}`) give finite sums that converge as ``n_theta``
  grows. Note that the Torrance--Sparrow :math:`1/\cos\theta_i` term of paper
  Eq. (38) is *not* integrable at the horizon unless its Gaussian factor
  vanishes there (:math:`\int_0 dz/z` diverges logarithmically); the sums stay
  finite but then grow like :math:`e^{-\pi^2/(16\sigma^2)}\log n_\theta`, which is
  negligible for small roughness :math:`\sigma` and a caveat for large ones (measured
  with :func:`project_normal_exitance`, ``a_0`` of the specular term for
  ``n_theta`` = 64/256/1024/4096: 4.24819/4.24822/4.24825/4.24828 at
  ``sigma = 0.2`` but 10.67/12.54/14.42/16.30 at ``sigma = 0.5``).
"""
from __future__ import annotations

from .albedo import directional_albedo
from .arguments import BasisLike, default_quadrature_sizes, infer_order
from .coefficients import ENERGY_EXCESS_TOLERANCE, energy_accuracy, reconstruct, truncate
from .convergence import ConvergenceError, ConvergenceWarning
from .least_squares import fit
from .normal_exitance import _theta_table, normal_exitance_energy, normal_exitance_to_isotropic, project_normal_exitance
from .projection import brdf_accuracy, brdf_energy, project

__all__ = [
    "project",
    "project_normal_exitance",
    "normal_exitance_to_isotropic",
    "normal_exitance_energy",
    "fit",
    "reconstruct",
    "truncate",
    "energy_accuracy",
    "brdf_energy",
    "brdf_accuracy",
    "ConvergenceError",
    "ConvergenceWarning",
    "directional_albedo",
    "default_quadrature_sizes",
    "infer_order",
]
