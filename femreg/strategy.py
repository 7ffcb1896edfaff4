r"""The two strategies of :func:`femreg.register` ("auto" and "paper") and the settings that differ between them:
the momentum regularisers' hourglass control and R_P_sigma's dilatation rule under "auto"
(:func:`effective_regularizer_options`), R_P_sigma's :math:`\bar\lambda` following the data under "auto"
(:func:`lambda_bar_follows_data`, :func:`data_lambda_bar`), the Gauss-Newton tolerance of "auto"
(:func:`component_tol`), and the user's regulariser turned into a fresh instance (:func:`fresh_regularizer`).
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np

from .errors import InputError
from .fields import element_strains, lateral_ratio, quadrant_ratios
from .material import LAMBDA_BAR_PLANE_STRAIN, LAMBDA_BAR_PLANE_STRESS
from .regularizers import make_regularizer

__all__ = ["STRATEGIES", "DEFAULT_HOURGLASS", "DEFAULT_MOMENTUM_STRESS_OPTIONS", "effective_regularizer_options",
           "component_tol", "fresh_regularizer", "LAMBDA_BAR_MODELS", "PLANE_STRAIN_RATIO", "lambda_bar_follows_data",
           "data_lambda_bar", "lambda_bar_stage", "AXIAL_SHARE", "RATIO_MAX"]

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


#: The two models R_P_sigma's :math:`\bar\lambda` chooses between (:func:`data_lambda_bar`): incompressible plane
#: stress (2, the paper's R_P_sigma) and R_P_eps's plane strain (9, nu = 0.45).  Measured on the plane-strain
#: inclusions of the robustness benchmark and benchmarks/inclusion_sizes.py (total strain error, one fixed
#: lambda_bar for all): 2 -> 4 -> 9 -> 20 -> 50: stiff 1 % paper 8.70 -> 8.03 -> 7.72 -> 7.68 -> 7.76 %, soft 4 %
#: paper 9.57 -> 8.61 -> 7.50 -> 7.16 -> 7.22 %, r 3 mm 7.12 -> 6.84 -> 6.07 -> 6.11 -> 6.49 %, r 8 mm 10.52 ->
#: 10.46 -> 9.93 -> 9.90 -> 12.64 %; the plane-stress inclusions got worse with every step above 2 (stiff 4 % paper
#: 8.20 -> 8.77 -> 11.19 %, soft 1 % L12 6.73 -> 7.41 -> 10.73 %).  Beyond 9 the 3 MHz and 8 mm cases lose again;
#: with the rule as it stands (re-solve, marking on the plane-stress solve), plane strain's 9 -> 15 -> 30: stiff 1 %
#: paper 8.04 -> 8.37 -> 9.11 %, r 3 mm 6.30 -> 6.52 -> 7.09 %, r 8 mm 10.00 -> 10.25 -> 10.81 %, r 2 mm under
#: 3 MHz 5.32 -> 5.63 -> 6.53 %, only the 15 MHz soft disk gaining (7.48 -> 7.27 -> 7.12 %).
LAMBDA_BAR_MODELS = (LAMBDA_BAR_PLANE_STRESS, LAMBDA_BAR_PLANE_STRAIN)
#: The ratio from which the data are read as plane strain: midway between plane stress's 1/2 and incompressible
#: plane strain's 1.  Plane-strain truths read 0.92-1.01 (47 pairs of benchmarks/inversion.py, 3-15 MHz, 15-30 dB),
#: plane-stress truths 0.47-0.52, 3D truths under a finite probe 0.52.  Not a continuous
#: :math:`\bar\lambda = 2r/(1-r)` between them: the plane-stress solve leans a weakly measured lateral strain
#: towards its own ratio, so a noisy pair reads its regulariser as much as its data (a 12 dB pair whose true
#: ratio is 0.32 read 0.57-0.66 over alpha 0.004-0.42, and following that reading, lambda_bar 2.7-3.8, raised its
#: total strain error 0.362 -> 0.375 at its best alpha, 0.453 -> 0.510 at 0.13).
PLANE_STRAIN_RATIO = 0.75


#: The data's ratio is read only where the median axial strain is at least this share of the field's RMS strain
#: (sqrt(mean(e_xx^2 + e_yy^2 + 2 e_xy^2)) over the elements): uniaxial compression 0.58-0.71, with as much
#: shear 0.53; pure shear and rotation, or bending (whose axial strain changes sign), read the ratio of noise.
AXIAL_SHARE = 0.25
#: A ratio above this (incompressible plane strain is 1) is no 2D model's: tissue flowing in from out of the plane
#: or a lateral strain of noise; R_P_sigma keeps its lambda_bar.  1 + the tolerance of femreg.invert's model="auto"
#: (AUTO_RATIO_TOLERANCE 0.2).  In vivo, seq299 frames 2 -> 5 read 1.05.
RATIO_MAX = 1.2


def lambda_bar_follows_data(strategy, regularizer, options=None, maxiter=1) -> bool:
    r"""Whether :func:`femreg.register` sets R_P_sigma's :math:`\bar\lambda` from the data
    (:func:`data_lambda_bar`): under ``strategy="auto"``, for ``regularizer="momentum-stress"`` given by name,
    unless the user's ``regularizer_options`` fix ``lambda_bar`` or ``maxiter`` is 0 (no solve asked)."""
    return (strategy == "auto" and isinstance(regularizer, str) and regularizer == "momentum-stress"
            and "lambda_bar" not in (options or {}) and int(maxiter) > 0)


def data_lambda_bar(mesh, u) -> tuple:
    r"""``(lambda_bar, ratio)``: the lateral-to-axial strain ratio ``ratio`` of the displacement ``u`` (nodal,
    interleaved, mm) on ``mesh`` (:func:`femreg.fields.lateral_ratio`) and the momentum regulariser's
    :math:`\bar\lambda` (eq:meq) of the 2D model it reads: plane strain (9) where the ratio and the ratio of each
    quadrant of the image (:func:`femreg.fields.quadrant_ratios`) lie from :data:`PLANE_STRAIN_RATIO` up to
    :data:`RATIO_MAX`, plane stress (2) otherwise (:data:`LAMBDA_BAR_MODELS`); a NaN ratio where the median axial
    strain is under :data:`AXIAL_SHARE` of the field's RMS strain.  The quadrants: simulated plane-strain fields
    read 0.89-1.11 in every quadrant (robustness benchmark, heterogeneous tissue), a freehand in vivo pair whose
    whole-image ratio read 1.05 (seq299 frames 2 -> 5) read 1.19 / 1.05 / 1.14 / 0.62, its lateral strain mostly
    noise (the other in vivo pairs: -0.35 to 0.64 or no axial strain to read).

    Why: R_P_sigma's A (eq:meq, :math:`\bar\lambda` = 2) is the stress of incompressible plane stress, whose lateral
    strain is half the axial one.  Where the tissue is held in plane strain (a long inclusion, a wide probe on deep
    tissue: the lateral strain as large as the axial one) the true field's A is not divergence-free (its pressure
    is not 2 div u), so it jumps across the element edges everywhere and the TV penalty (eq:dmreg2) bends the
    lateral and shear strain towards a plane-stress field away from the features; with plane strain's
    :math:`\bar\lambda` the smooth part of the field costs little again (measured at :data:`LAMBDA_BAR_MODELS`)."""
    e = element_strains(mesh.p, mesh.t, np.asarray(u, float))
    scale = np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2 + 2.0 * e[:, 2] ** 2))
    stress, strain = LAMBDA_BAR_MODELS
    if not abs(np.median(e[:, 0])) >= AXIAL_SHARE * scale:
        return stress, float("nan")     # no axial compression or stretch to read a ratio from
    ratio = lateral_ratio(e, mesh)
    # above RATIO_MAX: more lateral expansion than any 2D model has (out-of-plane motion or noise); and each
    # quadrant of the image must read plane strain too, or the reading is the lateral strain's noise
    quads = quadrant_ratios(e, mesh)
    plane_strain = all(PLANE_STRAIN_RATIO <= r <= RATIO_MAX for r in (ratio, *quads))
    return (strain if plane_strain else stress), ratio


def lambda_bar_stage(sol, user_reg, notes, resolve, *, follows: bool):
    r"""The :math:`\bar\lambda` stage of :func:`femreg.register`: with ``follows``
    (:func:`lambda_bar_follows_data` and a solve worth reading), the data's :math:`\bar\lambda`
    (:func:`data_lambda_bar`) of the solve ``sol``; where it differs from the regulariser's (``user_reg``, set to
    it), ``resolve(u)`` solves again from ``sol.u`` and a note goes to ``notes``.  Returns
    ``(marked, sol)``: the solve before (None when nothing changed), which the refinement marks on (its cuts were
    set on R_P_sigma's plane-stress jumps: :func:`femreg.refine.refine_passes`), and the solve now."""
    if not follows:
        return None, sol
    lb, ratio = data_lambda_bar(sol.mesh, sol.u)
    if lb == user_reg.lambda_bar:
        return None, sol
    user_reg.lambda_bar = lb
    notes.append(f"plane strain (lambda_bar {lb:g}) from the lateral-to-axial strain ratio {ratio:.2f} (plane "
                 f"stress 0.5, plane strain about 1)")
    new = resolve(sol.u)
    new.gn = dataclasses.replace(new.gn, nit=int(sol.gn.nit) + int(new.gn.nit))      # all iterations counted
    return sol, new


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
