"""Strain-magnitude regularisers R_eps and R_eps_i (paper arXiv:2508.19086, eq:saicr), written as scikit-fem weak forms
exactly as a user would write their own (see :class:`~femreg.regularizers.base.QuadraticFormRegularizer`)."""
from __future__ import annotations

import numpy as np
from skfem import BilinearForm
from skfem.helpers import ddot, div, sym_grad

from ..quadrature import ELEMENT_CENTRE_RULE as CENTRE_RULE
from ..quadrature import GAUSS_3X3
from .base import QuadraticFormRegularizer, register_regularizer


@BilinearForm
def strain_energy_form(u, v, w):
    """sym grad u : sym grad v  (integrand of R_eps, eq:saicr first term)."""
    return ddot(sym_grad(u), sym_grad(v))


@BilinearForm
def divergence_form(u, v, w):
    """div u * div v  (integrand of the incompressibility term of eq:saicr)."""
    return div(u) * div(v)


#: Fallback alphas, used only if femreg/data/default_alphas.json is missing.  The shipped defaults are the
#: values selected by the paper's procedure (``femreg study``, default 2 mm mesh, docs/study_report.md) for femreg's
#: normalisation (images divided by the reference RMS, lengths in mm, psi integrated over pixel areas in mm^2):
#: R_eps 17.8, R_eps_i 2.37; :mod:`femreg.regularizers` applies them to the classes below.
DEFAULT_ALPHA_STRAIN = 17.8
DEFAULT_ALPHA_STRAIN_INCOMPRESSIBLE = 2.37


class StrainRegularizer(QuadraticFormRegularizer):
    """R_eps[u] = alpha/2 ∫ sym grad u : sym grad u dΩ, 3x3 Gauss quadrature (eq:saicr with alpha_i = 0).

    Default alpha: femreg/data/default_alphas.json (17.8), :data:`DEFAULT_ALPHA_STRAIN` if it is missing."""

    name = "strain"
    default_alpha = DEFAULT_ALPHA_STRAIN

    def __init__(self, alpha: float | None = None):
        super().__init__([(strain_energy_form, 1.0, GAUSS_3X3)], alpha=alpha, name=self.name)


class StrainIncompressibleRegularizer(QuadraticFormRegularizer):
    """R_eps_i[u] = alpha/2 ∫ sym grad u : sym grad u + alpha_i/2 ∫ (div u)^2  (eq:saicr).

    The strain term uses 3x3 Gauss, the divergence term the 1-point centre rule (reduced integration, avoids
    locking); ``alpha_i = incompressibility_ratio * alpha`` (100 by default, as in the paper).
    Default alpha: femreg/data/default_alphas.json (2.37), :data:`DEFAULT_ALPHA_STRAIN_INCOMPRESSIBLE` if it is
    missing.
    """

    name = "strain-incompressible"
    default_alpha = DEFAULT_ALPHA_STRAIN_INCOMPRESSIBLE

    def __init__(self, alpha: float | None = None, incompressibility_ratio: float = 100.0):
        ratio = float(incompressibility_ratio)
        if not np.isfinite(ratio) or ratio < 0:
            raise ValueError(f"incompressibility_ratio must be finite and >= 0, got {incompressibility_ratio!r}")
        self.incompressibility_ratio = ratio
        super().__init__([(strain_energy_form, 1.0, GAUSS_3X3), (divergence_form, ratio, CENTRE_RULE)],
                         alpha=alpha, name=self.name)


register_regularizer(StrainRegularizer.name, StrainRegularizer)
register_regularizer(StrainIncompressibleRegularizer.name, StrainIncompressibleRegularizer)
