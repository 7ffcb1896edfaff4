"""The two strategies of :func:`femreg.register` ("auto" and "paper") and the settings that differ between them:
the momentum regularisers' hourglass control and R_P_sigma's dilatation rule under "auto"
(:func:`effective_regularizer_options`), the Gauss-Newton tolerance of "auto" (:func:`component_tol`), and the
user's regulariser turned into a fresh instance (:func:`fresh_regularizer`).
"""
from __future__ import annotations

import copy

import numpy as np

from .errors import InputError
from .regularizers import make_regularizer

__all__ = ["STRATEGIES", "DEFAULT_HOURGLASS", "DEFAULT_MOMENTUM_STRESS_OPTIONS", "effective_regularizer_options",
           "component_tol", "fresh_regularizer"]

#: ``strategy`` values of :func:`femreg.register`.
STRATEGIES = ("auto", "paper")


def component_tol(tol: float, u0) -> float:
    """Gauss-Newton tolerance of ``strategy="auto"``: ``tol`` for the smaller displacement component.

    The stopping rule ``||du|| / ||u|| < tol`` is dominated by the larger (usually axial) component; from the
    pyramid's close start it stopped while the lateral one, often ten times smaller, still moved (plane-stress
    inclusion pair, R_P_sigma alpha 0.01: 2 iterations, lateral error 12.13 %; converged 12.34 %, and the
    ranking of the alphas changed).  So the tolerance is scaled by ||u0_small|| / ||u0||, at most 10x tighter."""
    u0 = np.asarray(u0, float)
    n = float(np.linalg.norm(u0))
    if not n > 0:
        return tol
    small = min(float(np.linalg.norm(u0[0::2])), float(np.linalg.norm(u0[1::2])))
    return float(tol * min(1.0, max(0.1, small / n)))


#: Hourglass-control weight (relative to alpha) of the momentum regularisers with ``strategy="auto"``: the edge
#: jumps of eq:Ae7 do not see the node-to-node checkerboard modes of bilinear quads (see
#: :class:`femreg.regularizers.momentum.MomentumRegularizer`) and on real data they show as alternating element
#: columns in e_yy.  Measured on the in vivo frames 1 -> 6 (R_P_sigma, default mesh; femreg.quality.hourglass,
#: RMS of the u_y mode): seq299 weight 0 / 1 / 10 / 100 -> 40 / 36 / 26 / 12 um with NCC after 0.791 / 0.791 /
#: 0.791 / 0.800 (stripes gone only at 100); seq304 9.3 / 9.2 / - / 5.7 um, NCC 0.883 at all weights.  On
#: synthetic pairs (1-3 % compression, shear, 3-12 MHz) 100 also lowered the total strain error (e.g. shear
#: 3.0 -> 1.3 %, 3 % compression 1.4 -> 0.4 %).  The mode is a mesh artefact, so the weight costs no accuracy.
DEFAULT_HOURGLASS = 100.0
#: R_P_sigma's options with ``strategy="auto"`` (``strategy="paper"`` keeps the paper's form): the dilatation part
#: of A at the element centre, as the paper does for R_P_eps only (appendix, "Reduced Form of TV Momentum
#: Regularization": reduced integration against locking), and hourglass control 1000.  At the edge midpoint the
#: dilatation of a bilinear element carries its bending modes, which the jump penalty then holds back: the lateral
#: strain around an inclusion is flattened.  The centre value no longer sees the hourglass part of those modes, so
#: the hourglass weight goes up with it.  Measured, total strain error (recovered strain), edge + 100 -> centre +
#: 100 -> centre + 1000: robustness benchmark, soft plane-strain 1 % at 15 MHz 16.6 -> 12.5 -> 13.0, soft
#: plane-stress 1 % at 12 MHz 14.6 -> 10.4 -> 10.5, stiff plane-stress 1 % at 3 MHz 15.1 -> 12.9 -> 12.9, stiff
#: plane-strain 1 % 18.1 -> 13.5 -> 14.3, bending 6.5 -> 4.3 -> 4.4, uniform compression 0.1-1.9 -> 0.1-1.6 ->
#: 0.1-1.1; 3D HI frames 1 -> 7 12.1 -> 9.9 -> 10.1; on a 24 x 20 mm crop around the inclusion (plane stress,
#: frames 1 -> 7) 23.2 -> 25.9 -> 22.6, but at 0.27 % strain (frames 1 -> 4) 27.9 -> 45.0 -> 39.7 (shear strain:
#: small ROI, little lateral information); in vivo frames 1 -> 6 NCC after 0.813 / 0.898 -> 0.813 / 0.898 ->
#: 0.808 / 0.891 (seq299 / seq304), row alternation of e_xx 1.30 / 1.28 -> 1.28 / 1.19 -> 1.18 / 0.88.
DEFAULT_MOMENTUM_STRESS_OPTIONS = {"dilatation": "centre", "hourglass": 1000.0}


def effective_regularizer_options(strategy, regularizer, options=None) -> dict:
    """The regulariser options ``register`` uses: the user's, with hourglass control of the momentum
    regularisers (:data:`DEFAULT_HOURGLASS`; R_P_sigma: :data:`DEFAULT_MOMENTUM_STRESS_OPTIONS`) added under
    ``strategy="auto"``."""
    opts = dict(options or {})
    if strategy == "auto" and isinstance(regularizer, str) and regularizer.startswith("momentum"):
        defaults = DEFAULT_MOMENTUM_STRESS_OPTIONS if regularizer == "momentum-stress" else \
            {"hourglass": DEFAULT_HOURGLASS}
        for k, v in defaults.items():
            opts.setdefault(k, v)
    return opts


def fresh_regularizer(spec, alpha, options):
    """A new regulariser instance carrying the user's alpha (never the caller's own object)."""
    try:
        reg = make_regularizer(spec, alpha=alpha, **(options or {}))
    except InputError:
        raise
    except (ValueError, TypeError) as exc:
        raise InputError(str(exc)) from None
    return copy.copy(reg) if reg is spec else reg
