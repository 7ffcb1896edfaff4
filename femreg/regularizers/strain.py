"""Strain-magnitude regularisers R_eps and R_eps_i (paper eq:saicr), written as scikit-fem weak forms
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


#: Default alphas for femreg's normalisation (both images divided by the reference RMS, lengths in mm, psi
#: integrated over pixel areas in mm^2) and the default 2 mm mesh.  Chosen the paper's way (minimum total
#: strain error of a single-frame registration at 0.4-0.8 % compression) on the synthetic paper-geometry pair
#: of benchmarks/bench_register.py --study (SNR 12 dB): R_eps total strain error 25.4 / 19.2 / 23.0 / 30.6 % at
#: alpha 10 / 30 / 100 / 300; R_eps_i 47.9 / 39.7 / 43.2 / 46.1 % at alpha 1 / 3 / 10 / 30.  Provisional until the
#: alpha-selection issue repeats this on the simulated sequences.
DEFAULT_ALPHA_STRAIN = 30.0
DEFAULT_ALPHA_STRAIN_INCOMPRESSIBLE = 3.0


class StrainRegularizer(QuadraticFormRegularizer):
    """R_eps[u] = alpha/2 ∫ sym grad u : sym grad u dΩ, 3x3 Gauss quadrature (eq:saicr with alpha_i = 0).

    Default alpha: :data:`DEFAULT_ALPHA_STRAIN` (see there for the study)."""

    name = "strain"
    default_alpha = DEFAULT_ALPHA_STRAIN

    def __init__(self, alpha: float | None = None):
        super().__init__([(strain_energy_form, 1.0, GAUSS_3X3)], alpha=alpha, name=self.name)


class StrainIncompressibleRegularizer(QuadraticFormRegularizer):
    """R_eps_i[u] = alpha/2 ∫ sym grad u : sym grad u + alpha_i/2 ∫ (div u)^2  (eq:saicr).

    The strain term uses 3x3 Gauss, the divergence term the 1-point centre rule (reduced integration, avoids
    locking); ``alpha_i = incompressibility_ratio * alpha`` (100 by default, as in the paper).
    Default alpha: :data:`DEFAULT_ALPHA_STRAIN_INCOMPRESSIBLE`.
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
