r""":math:`\bar\lambda` of the momentum equation eq:cEq, :math:`\nabla\cdot[\mu(\bar\lambda\,(\nabla\cdot u) I +
\nabla u + \nabla u^T)] = 0`, the ratio :math:`\lambda/\mu` of the (effective) Lame constants, in one place for
the momentum regularisers (:mod:`femreg.regularizers.momentum`) and the modulus inversion (:mod:`femreg.inversion`).

Plane strain: :math:`\bar\lambda = 2\nu/(1-2\nu)` (:math:`\lambda = E\nu/((1+\nu)(1-2\nu))`, :math:`\mu =
E/(2(1+\nu))`); plane stress, with the effective :math:`\lambda^* = 2\lambda\mu/(\lambda+2\mu)`:
:math:`\bar\lambda = 2\nu/(1-\nu)`, 2 for incompressible tissue (:math:`\nu = 1/2`).  Poisson's ratio must lie in
:math:`(-1, 1/2)` for plane strain (at 1/2 :math:`\bar\lambda` is infinite) and :math:`(-1, 1/2]` for plane stress.
"""
from __future__ import annotations

import math

from .errors import InputError

__all__ = ["MODELS", "lambda_bar", "LAMBDA_BAR_PLANE_STRAIN", "LAMBDA_BAR_PLANE_STRESS", "model_ratio",
           "lambda_bar_from_ratio"]

#: The two 2D models.
MODELS = ("plane-stress", "plane-strain")
#: :math:`\bar\lambda` of R_P_eps: plane strain, nu = 0.45 -> 2 nu / (1 - 2 nu) = 9 (paper, "Registration").
LAMBDA_BAR_PLANE_STRAIN = 9.0
#: :math:`\bar\lambda` of R_P_sigma and of the plane-stress inversion: incompressible, nu = 1/2 -> 2.
LAMBDA_BAR_PLANE_STRESS = 2.0


def lambda_bar(model: str, poisson: float) -> float:
    r""":math:`\bar\lambda` (dimensionless) of ``model`` ("plane-strain" or "plane-stress") for Poisson's ratio
    ``poisson``; :class:`~femreg.errors.InputError` (a ValueError) naming the model's range otherwise."""
    if model not in MODELS:
        raise InputError(f"unknown model {model!r}; choose one of {MODELS}")
    try:
        nu = float(poisson)
    except (TypeError, ValueError):
        raise InputError(f"poisson must be a number, got {poisson!r}") from None
    strain = model == "plane-strain"
    if not (math.isfinite(nu) and -1.0 < nu and (nu < 0.5 if strain else nu <= 0.5)):
        raise InputError(f"poisson must lie in (-1, 0.5{')' if strain else ']'} for {model}, got {poisson!r}")
    return 2.0 * nu / (1.0 - 2.0 * nu) if strain else 2.0 * nu / (1.0 - nu)


def model_ratio(lam_bar: float) -> float:
    r"""The lateral-to-axial strain ratio :math:`r = \bar\lambda/(\bar\lambda + 2)` of uniaxial stress in the 2D
    model (:math:`\sigma_{yy} = \mu(\bar\lambda\,\mathrm{tr}\,\varepsilon + 2\varepsilon_{yy}) = 0`):
    1/2 for incompressible plane stress, :math:`\nu/(1-\nu)` for plane strain."""
    return lam_bar / (lam_bar + 2.0)


def lambda_bar_from_ratio(ratio: float) -> float:
    r""":math:`\bar\lambda = 2r/(1-r)`, the inverse of :func:`model_ratio`: the 2D model whose uniaxial stress
    expands laterally as the data do (``ratio`` :math:`r = -\varepsilon_{yy}/\varepsilon_{xx}`, dimensionless);
    infinite at r >= 1, NaN for a NaN ratio."""
    r = float(ratio)
    if math.isnan(r):
        return math.nan
    return math.inf if r >= 1.0 else 2.0 * r / (1.0 - r)
