r"""``alpha="auto"``: the regularisation weight of eq:objf chosen from the image pair alone (no ground truth).

Rule (default ``"quasi-optimality"``): the quasi-optimality criterion (A. N. Tikhonov, V. B. Glasko, USSR Comput.
Math. Math. Phys. 5 (1965) 93-107; F. Bauer, M. Reiss, Inverse Problems 24 (2008) 055009,
doi:10.1088/0266-5611/24/5/055009): on the geometric grid of candidates take the alpha where the result changes
least from one candidate to the next, ``min_k ||e(alpha_{k+1}) - e(alpha_k)||`` over the recovered nodal strains
(:func:`femreg.fields.recovered_strains`, the quantity elastography reports), the smaller alpha of that pair,
interior pairs only (the grid's end pairs are not candidates: a minimum there only says the grid is too short),
and below the last interior local maximum of the change (:func:`quasi_optimal_index`): past that maximum the
change shrinks only because the result saturates towards the regulariser's null space, which the theory
excludes.  A registration that reports failure is no candidate (:func:`successful_stretch`).  It needs no noise
level.  Measured on the paper's six data sets x four regularisers (frames 1 -> 7, 2 mm mesh, total strain error
against the truth-best alpha of the same grid): within 15 % on 24 of 24 (median 1.00, max 1.13; 24 of 24, max
1.14, in another realisation of the data sets, benchmarks/autoalpha.py --paper-seed 1); without the
saturation cut 19 of 24 (R_eps_i 1 of 6, max 1.94: its change falls steadily once the incompressibility term
dominates), and the discrepancy rule below reached 11 of 24 (median 1.47, max 3.31) -- for the momentum terms the
image term hardly changes with the lateral field, so a misfit-based rule allows 3-10x too much regularisation.
The cut assumes the grid does not reach down to where the result stops changing at small alpha too (the
registration there is no longer limited by the regulariser): with the grid extended half a decade, one decade and
two decades below the default one, the paper's set fell to 22, 17 and 7 of 24 (the plain rule: 19, 19, 14).

Rule ``"discrepancy"``: Morozov's discrepancy principle (V. A. Morozov, Soviet Math. Dokl. 7 (1966)
414-417; P. C. Hansen, *Discrete Inverse Problems*, SIAM 2010, ch. 5, doi:10.1137/1.9780898718836) with the noise
level estimated from the images themselves: take the largest :math:`\alpha` of the grid whose image term is within
what the best fit of the grid could have absorbed by fitting noise,

.. math::  2\psi(u_\alpha) - 2\psi_{\min} \le c\,\sigma_w^2\,T_{\min},\qquad
           T(\alpha) = \mathrm{tr}\big(H_\psi\,(H_\psi + H_R(u_\alpha))^{-1}\big)

* :math:`\psi` is the image term of eq:objf (eq:IR) at the registered field, :math:`H_\psi = J^T W J` its
  Gauss-Newton Hessian (fixed reference gradient, eq:wfnew) and :math:`H_R` the regulariser's Hessian at
  :math:`u_\alpha` (for the TV momentum terms the lagged-diffusivity Hessian eq:dmreg4): :math:`T` is the number
  of degrees of freedom the images effectively fit (the trace of the influence matrix);
* :math:`\sigma_w^2 = 2\psi_{\min} / (n - T_{\min})`: the residual variance per pixel (times the pixel weight
  dx dy) of the best-fitting run, corrected for the degrees of freedom it fitted (the regression estimate);
* :math:`c`: the residual is not white (decorrelated speckle lives in the PSF band, like the image gradient that
  builds J), so the noise a fitted degree of freedom absorbs is :math:`c` times its white-noise value; with
  :math:`S_r` and :math:`S_g` the power spectra of the best fit's residual image and of the reference gradient,
  :math:`c = \overline{S_r S_g} / (\overline{S_r}\;\overline{S_g})` (1 for white noise).

``rule="upre"``: the minimum of the unbiased predictive risk estimate :math:`U(\alpha) = 2\psi + 2c\sigma_w^2 T`
(Mallows' :math:`C_p`, Technometrics 15 (1973) 661-675, doi:10.1080/00401706.1973.10489103; C. R. Vogel,
*Computational Methods for Inverse Problems*, SIAM 2002, ch. 7, doi:10.1137/1.9780898717570).  It minimises the
error of the *predicted image*, which the axial component dominates, and picked alphas up to 10x too small for
R_eps on the paper's data (the lateral strain needs more); the discrepancy rule never missed by more than a factor
1.45 in total strain error there.

U is evaluated on a half-decade grid around the regulariser's default alpha (``decades``), every point one full
:func:`femreg.register` call; the grid minimum is returned together with the registration at it (so
``register(alpha="auto")`` costs ``n_registrations`` registrations, i.e. ``n_registrations - 1`` extra).

Volumes: the same rules on the same grid, the candidates registered by :func:`femreg.volume.register_volume` and
the image term read by :func:`femreg.volume.voxel_image_term` (``image_term=``; frames: :func:`pixel_image_term`);
the strain change runs over the six recovered nodal strain components.  ``femreg.register`` and ``femreg.track``
pass both for 3D arrays.  Measured on small simulated volumes: benchmarks/autoalpha_volume.py (docs/autoalpha.md).

Fan frames (scan-converted convex / phased B-mode, ``data_mask`` of :func:`femreg.register`): the candidates are
registered with the fan's mask, the image term is built with it (:func:`pixel_image_term`) and the strain change
runs over the nodes inside the fan (:func:`fan_nodes`), so the choice sees what the registration sees.  Measured on
8 simulated fan pairs (benchmarks/autoalpha_fan.py): ``track``'s candidates, registered before without the fan's
weights, failed on 14 of 56 (all 7 on one pair), 2 of 56 with them; axial strain error in the fan at the chosen
alpha, mean 9.64 -> 9.63 %, max over the grid's best 2.16 -> 1.73 (median 1.24 -> 1.28).

Measured on the paper's six simulated pairs (frames 1 -> 7, 2 mm mesh) against the ground-truth-best alpha of the
same grid: see docs/study_report.md ("Automatic alpha").
"""
from __future__ import annotations

import contextlib
import copy
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .echo import as_data_mask
from .errors import InputError, pass_as
from .gnsolve import image_term as ssd_term
from .image import SplineImage, normalize_pair, validate_image, validate_spacing
from .regularizers import Regularizer, make_regularizer
from .result_base import AutoAlpha
from .scaling import effective_alpha
from .solver import GN_STRAIN_TOL_TIGHT
from .strategy import effective_regularizer_options

__all__ = ["AutoAlpha", "choose_alpha", "register_auto", "DEFAULT_DECADES", "influence_trace", "quasi_optimal_index",
           "successful_stretch", "ImageTerm", "pixel_image_term", "PROGRESS", "showing_progress", "fan_nodes"]

#: The registration function :func:`choose_alpha` calls (``register=`` overrides it): :func:`femreg.register`, set
#: by :mod:`femreg.registration` when it is imported (it calls this module for ``alpha="auto"``; this module never
#: imports it, so the two form no import cycle).
ENGINE = None

#: Exponents (decades) of the candidate grid relative to the regulariser's default alpha: 10^-1.5 ... 10^1.5.
DEFAULT_DECADES = (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5)
#: Above this many unknowns the trace T is estimated (Hutchinson, seeded Rademacher probes) instead of exact.
EXACT_TRACE_MAX_DOF = 3000
TRACE_PROBES = 40


def _auto_words() -> str:
    """How a message names the automatic choice: the argument, or the flag on the command line."""
    return pass_as("alpha='auto'", "--alpha auto")


def influence_trace(Hd, Hr, *, seed: int = 0) -> float:
    """T = tr(Hd (Hd + Hr)^-1) (= tr((Hd + Hr)^-1 Hd)); exact (dense) for small systems, else Hutchinson's estimator
    with :data:`TRACE_PROBES` seeded Rademacher vectors and one sparse LU."""
    n = Hd.shape[0]
    H = (Hd + Hr).tocsc() + sp.identity(n, format="csc") * 1e-12 * abs(Hd.diagonal()).max()
    if n <= EXACT_TRACE_MAX_DOF:
        return float(np.trace(np.linalg.solve(H.toarray(), Hd.toarray())))
    lu = spla.splu(H)
    Z = np.random.default_rng(seed).choice([-1.0, 1.0], size=(n, TRACE_PROBES))
    return float(np.mean(np.sum(Z * lu.solve(np.asarray(Hd @ Z)), axis=0)))


def _correlation_factor(residual, gradients) -> float:
    """c of the module docstring from the residual and the reference gradient components (arrays of one shape,
    2D frames or 3D voxel blocks): their power spectra over every axis."""
    Sr = np.abs(np.fft.rfftn(residual)) ** 2
    Sg = sum(np.abs(np.fft.rfftn(g)) ** 2 for g in gradients)
    den = np.mean(Sr) * np.mean(Sg)
    return float(np.mean(Sr * Sg) / den) if den > 0 else 1.0


@dataclass
class ImageTerm:
    """What the rules read of the image term psi (eq:IR) on the registrations' mesh: ``data`` (``energy(u)``,
    ``hessian()``), ``n_samples`` (pixels or voxels it sums over), ``residual_image(u)`` the residual as an array
    and ``gradients`` the reference gradient components on the same samples (for :func:`_correlation_factor`)."""

    data: object
    n_samples: int
    residual_image: object
    gradients: tuple


def pixel_image_term(reference_image, moving_image, mesh, register_kwargs) -> ImageTerm:
    """The :class:`ImageTerm` of a frame pair, built as :func:`femreg.register` builds its image term (the
    ``image_term`` of :func:`choose_alpha` for 2D frames; :func:`femreg.volume.voxel_image_term` for volumes).

    A ``data_mask`` in ``register_kwargs`` (a fan, :func:`femreg.echo.as_data_mask`) enters as in the registration:
    the pair normalised over the fan, eq:IR weight 0 outside its ``weights``, and ``n_samples``, the residual and
    the gradients over the weighted pixels only (the fill's constant and the fan's edge are no speckle)."""
    spacing, origin = validate_spacing(register_kwargs["spacing"], register_kwargs.get("origin", (0.0, 0.0)))
    ref = validate_image(reference_image, "reference image")
    mov = validate_image(moving_image, "moving image")
    fan = as_data_mask(register_kwargs.get("data_mask"), ref.shape, spacing)
    if register_kwargs.get("normalize", True):
        ref, mov, _ = normalize_pair(ref, mov, mask=None if fan is None else fan.inside)
    I1, I2 = SplineImage(ref, spacing, origin), SplineImage(mov, spacing, origin)
    if fan is not None:
        I1.weights_mask = fan.weights       # read by femreg.gnsolve.image_term
    data = ssd_term(I1, I2, mesh, ref.shape, spacing, origin, offset=register_kwargs.get("offset"))
    quad = data.quad
    if data.offset is None:
        grads = I1.gradient_at_pixels()
    else:
        g = np.zeros((2, ref.size))
        g[:, quad.index] = data.ref_gradient.T
        grads = (g[0].reshape(ref.shape), g[1].reshape(ref.shape))
    n_samples = quad.n_pixels
    if fan is not None:
        grads = tuple(np.where(fan.weights, gr, 0.0) for gr in grads)
        n_samples = int(np.count_nonzero(data.w))
    w = None if fan is None else (data.w > 0)

    def residual_image(u):
        r = np.zeros(ref.size)
        r[quad.index] = data.residual(u) if w is None else np.where(w, data.residual(u), 0.0)
        return r.reshape(ref.shape)

    return ImageTerm(data=data, n_samples=n_samples, residual_image=residual_image, gradients=tuple(grads))


def fan_nodes(mesh, register_kwargs, shape):
    """Bool (n_nodes,): the mesh nodes whose nearest pixel of the frames (``shape``) lies inside the fan of
    ``register_kwargs["data_mask"]`` (:func:`femreg.echo.as_data_mask`; nodes off the grid count as outside);
    None without a mask.  The strain change of the quasi-optimality rule runs over these nodes: outside the fan
    the field is the regulariser's alone, which changes with alpha whatever the data say."""
    spacing, origin = validate_spacing(register_kwargs["spacing"], register_kwargs.get("origin", (0.0, 0.0)))
    fan = as_data_mask(register_kwargs.get("data_mask"), shape, spacing)
    if fan is None:
        return None
    idx = np.rint((np.asarray(mesh.p, float).T - origin) / spacing).astype(int)
    ok = np.all((idx >= 0) & (idx < np.asarray(shape)), axis=1)
    inside = np.zeros(len(idx), bool)
    inside[ok] = fan.inside[idx[ok, 0], idx[ok, 1]]
    return inside if inside.any() else None


RULES = ("quasi-optimality", "discrepancy", "upre")


def quasi_optimal_index(change) -> int:
    """Index k of the chosen candidate from ``change[k] = ||e(alpha_{k+1}) - e(alpha_k)||`` (increasing alpha).

    The smaller alpha of the steadiest interior pair, searched below the last interior local maximum of the
    change: beyond it the change falls only because the result saturates towards the regulariser's null space
    (rigid motion for R_eps and R_eps_i, momentum-free fields for R_P), the regime the quasi-optimality theory
    excludes (its grid stops where the regularisation dominates every data mode; Bauer & Reiss 2008, sec. 2).
    Without an interior local maximum: all interior pairs.
    """
    d = np.asarray(change, float)
    if d.ndim != 1 or d.size < 3:
        raise InputError("the quasi-optimality rule needs at least 3 strain changes (4 candidates)")
    peaks = [k for k in range(1, d.size - 1) if d[k] >= d[k - 1] and d[k] > d[k + 1]]
    hi = peaks[-1] if peaks and peaks[-1] > 1 else d.size - 1
    return 1 + int(np.argmin(d[1:hi]))


def successful_stretch(success) -> tuple[int, int]:
    """(lo, hi): the longest run ``success[lo:hi]`` of True (the first of equal runs); (0, n) when all are True
    and, when none is, (n // 2, n // 2 + 1) -- the grid centre, whose result then reports the failure."""
    s = list(success)
    best, start = (0, 0), None
    for i, ok in enumerate(s + [False]):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    return best if best[1] > best[0] else (len(s) // 2, len(s) // 2 + 1)


#: Whether :func:`choose_alpha` shows a progress bar over its candidates when not told (``progress=None``);
#: the command line turns it on for its commands (:func:`showing_progress`), a library call stays silent.
PROGRESS = False


@contextlib.contextmanager
def showing_progress(enabled: bool = True):
    """``with showing_progress(): ...``: :func:`choose_alpha` calls in the block (also those of
    ``femreg.register(alpha="auto")``) show a tqdm bar over the candidate alphas on stderr."""
    global PROGRESS
    previous, PROGRESS = PROGRESS, bool(enabled)
    try:
        yield
    finally:
        PROGRESS = previous


def choose_alpha(reference_image, moving_image, *, decades=DEFAULT_DECADES, base_alpha=None,
                 rule="quasi-optimality", keep_results=False, image_term=None, progress=None, **register_kwargs):
    """Choose alpha for one pair (module docstring).

    Parameters
    ----------
    reference_image, moving_image : the pair, as for :func:`femreg.register` (frames or volumes; a volume pair
        needs ``register=femreg.volume.register_volume`` and ``image_term=femreg.volume.voxel_image_term``,
        which :func:`femreg.register` passes for ``alpha="auto"``).
    decades : exponents of the candidate grid, ``base_alpha * 10**d``.
    base_alpha : centre of the grid; default the regulariser's default alpha.
    rule : "quasi-optimality" (default), "discrepancy" or "upre" (module docstring).
    keep_results : also return every grid registration (``AutoAlpha.results``).
    image_term : callable ``(reference, moving, mesh, register_kwargs) -> ImageTerm``; default
        :func:`pixel_image_term` (frames); volumes: :func:`femreg.volume.voxel_image_term`.
    progress : bool or None
        A tqdm bar on stderr over the candidates (two steps per alpha: its registration and its influence
        trace); None: :data:`PROGRESS`.
    **register_kwargs : every other keyword argument of :func:`femreg.register` (spacing, regularizer, mesh, ...);
        ``alpha`` must be absent or "auto"; ``register=`` another registration function of the same signature
        (default :data:`ENGINE`, i.e. :func:`femreg.register`).

    Returns
    -------
    AutoAlpha (``result`` is the registration at the chosen alpha; cost ``n_registrations`` registrations).
    """
    register = register_kwargs.pop("register", None) or ENGINE
    a = register_kwargs.pop("alpha", "auto")
    if a not in (None, "auto"):
        raise InputError(f"choose_alpha chooses alpha itself; got alpha={a!r}")
    decades = np.asarray(decades, float)
    if rule not in RULES:
        raise InputError(f"rule must be one of {RULES}, got {rule!r}")
    if decades.ndim != 1 or decades.size < 3 or not np.all(np.isfinite(decades)):
        raise InputError("decades must hold at least 3 finite exponents")
    if rule == "quasi-optimality" and decades.size < 4:
        raise InputError("the quasi-optimality rule needs at least 4 candidates (decades)")
    regularizer = register_kwargs.get("regularizer", "momentum-stress")
    options = register_kwargs.get("regularizer_options") or {}
    if base_alpha is None:
        base_alpha = (regularizer.alpha if isinstance(regularizer, Regularizer)
                      else make_regularizer(regularizer, **options).alpha)
    alphas = float(base_alpha) * 10.0 ** np.sort(decades)

    if register_kwargs.get("strain_tol") is None:     # the rules compare strains 1-2 % apart: settle further
        register_kwargs["strain_tol"] = GN_STRAIN_TOL_TIGHT
    bar = None
    if PROGRESS if progress is None else progress:
        from .progress import bar as make_bar

        # two steps per candidate: its registration, then its influence trace (a dense solve on small meshes,
        # often the longer of the two)
        bar = make_bar(total=2 * alphas.size, desc="alpha auto", unit="step")

    def step(text, refresh=True):
        if bar is not None:
            bar.set_postfix_str(text, refresh=refresh)

    def finished(text):
        # the count moves with the step's own name in the past tense: a line written on the count (a log) names
        # the step it counts, not the one starting next
        if bar is not None:
            step(text, refresh=False)
            bar.update(1)

    try:
        results = []
        for al in alphas:
            step(f"registering at alpha {al:.3g}")
            results.append(register(reference_image, moving_image, alpha=float(al), **register_kwargs))
            finished(f"registered at alpha {al:.3g}")

        # the image term and its Hessian on the registrations' mesh (same construction as register /
        # register_volume)
        mesh = results[0].mesh
        step("image term for the scores")
        term = (image_term or pixel_image_term)(reference_image, moving_image, mesh, register_kwargs)
        data = term.data
        Hd = data.hessian().tocsr()

        psi, dof = np.empty(alphas.size), np.empty(alphas.size)
        opts = effective_regularizer_options(register_kwargs.get("strategy", "auto"), regularizer, options)
        for i, (al, res) in enumerate(zip(alphas, results)):
            step(f"scoring alpha {al:.3g}")
            reg = (copy.copy(regularizer) if isinstance(regularizer, Regularizer)
                   else make_regularizer(regularizer, **opts))
            a_eff = getattr(res, "alpha_effective", float("nan"))
            reg.alpha = a_eff if np.isfinite(a_eff) else effective_alpha(al, mesh)
            reg.setup(mesh)
            psi[i] = data.energy(res.u)
            dof[i] = influence_trace(Hd, sp.csr_matrix(reg.hessian(res.u)))
            finished(f"scored alpha {al:.3g}")
    finally:
        if bar is not None:
            bar.set_postfix_str(f"{alphas.size} candidates", refresh=False)
            bar.close()

    n = term.n_samples
    # a registration that reports failure is no candidate: the rules run on the longest unbroken stretch of
    # successful ones (the change between two candidates either side of a failure means nothing)
    succeeded = [bool(getattr(res, "success", True)) for res in results]
    lo, hi = successful_stretch(succeeded)
    i0 = lo + int(np.argmin(psi[lo:hi]))             # the best image fit among them
    sigma2 = 2.0 * psi[i0] / max(n - dof[i0], 1.0)
    c = _correlation_factor(term.residual_image(results[i0].u), term.gradients)
    upre = 2.0 * psi + 2.0 * c * sigma2 * dof
    # over the fan's nodes where the registrations have one (as they report strains: NaN outside the fan)
    nodes = fan_nodes(mesh, register_kwargs, np.shape(reference_image)) if np.ndim(reference_image) == 2 else None
    strains = [(res.nodal_strain if nodes is None else res.nodal_strain[nodes]).ravel() for res in results]
    change = np.array([np.linalg.norm(strains[k + 1] - strains[k]) for k in range(len(strains) - 1)])
    if rule == "upre":
        k = lo + int(np.argmin(upre[lo:hi]))
    elif rule == "quasi-optimality":
        k = lo + quasi_optimal_index(change[lo:hi - 1]) if hi - lo >= 4 else lo + (hi - lo - 1) // 2
    else:   # discrepancy: the largest alpha whose misfit stays within what the best fit could have absorbed
        ok = np.flatnonzero(2.0 * (psi[lo:hi] - psi[i0]) <= c * sigma2 * dof[i0])
        k = lo + int(ok.max()) if ok.size else lo + int(np.argmin(psi[lo:hi]))
    n_ok = sum(bool(getattr(res, "success", True)) for res in results)
    if n_ok == 0:
        import warnings

        warnings.warn(f"{_auto_words()}: none of the {alphas.size} candidate registrations succeeded; no alpha "
                      f"was chosen, the grid centre {alphas[k]:.4g} is used", RuntimeWarning, stacklevel=2)
    return AutoAlpha(alpha=float(alphas[k]), alphas=alphas, psi=psi, dof=dof, upre=upre, c=c, sigma2=float(sigma2),
                     n_registrations=int(alphas.size), result=results[k], rule=rule,
                     results=results if keep_results else None, strain_change=change, n_successful=n_ok)


def register_auto(reference_image, moving_image, **register_kwargs):
    """:func:`femreg.register` with ``alpha="auto"``: the registration at the alpha of :func:`choose_alpha`;
    the choice is in ``result.auto_alpha`` (an :class:`AutoAlpha` without its result).  When every candidate
    fails, the result (at the grid centre) fails and its message says that no alpha was chosen."""
    a = register_kwargs.get("alpha")
    if not (isinstance(a, str) and a == "auto"):
        raise InputError(f"alpha must be a number or 'auto', got {a!r}")
    choice = choose_alpha(reference_image, moving_image, **register_kwargs)
    res = choice.result
    choice.result = None
    res.auto_alpha = choice
    if choice.n_successful == 0:    # the failure is the registration's; the message also says no alpha was chosen
        res.success = False
        res.message = (f"FAILED: {_auto_words()} found no successful candidate ({choice.n_registrations} registrations "
                       f"failed), the result at the grid centre alpha {choice.alpha:.4g} is returned: "
                       + res.message.removeprefix("FAILED: "))
    return res
