"""The initial-guess stage of :func:`femreg.register`: the start u_1 on the final mesh, from the coarse-to-fine
envelope pyramid (:mod:`femreg.pyramid`, ``strategy="auto"``), the paper's block matching with its coarse pass
(:mod:`femreg.paperguess`, ``strategy="paper"``), zero, or the user's field.  On a sequence (``offset`` S) the
pyramid and the block matching compare I_k(x + S) with I_{k+1}(x + S) on the pixel grid.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .blockmatch import BlockMatchResult
from .image import pixel_axes
from .paperguess import paper_initial_guess, wants_coarse_pass
from .pyramid import PyramidGuess, PyramidSearch, image_settings, pyramid_search, pyramid_solve
from .result import displacement_at, nodal_values
from .result_base import FRESH_NOTE

__all__ = ["InitialGuess", "initial_guess", "start_search", "INITIAL_NAMES", "Previous", "previous_or_fresh"]

#: The named starts of ``register(initial=...)``.
INITIAL_NAMES = ("pyramid", "blockmatch", "zero")


@dataclass
class InitialGuess:
    """Output of :func:`initial_guess`: the nodal start ``u0`` (2 n_nodes,) mm; the block matching (or None); the
    pyramid's guess (or None); ``coarse_u0``, the pyramid's field at the nodes (the coarse level the repair
    trusts, or None); the speckle statistics and pyramid settings (computed here when the pyramid needed them);
    seconds per sub-stage."""

    u0: np.ndarray
    blockmatch: BlockMatchResult | None = None
    pyramid: PyramidGuess | None = None
    coarse_u0: np.ndarray | None = None
    stats: object = None
    settings: object = None
    timings: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Previous:
    """A start from an earlier solution that these frames may not bear out (an accumulated track's previous
    increment, :func:`femreg.track`): ``u`` (2 n_nodes,) mm is used unless the frames match at least as well with
    no motion at all (:func:`previous_or_fresh`); then ``fresh``, the strategy's own start (None; a name of
    :data:`INITIAL_NAMES`), is used instead."""

    u: object
    fresh: object = None


def previous_or_fresh(initial, term_for, mesh):
    """``(initial, note, term)``: the start :func:`femreg.register` uses for ``initial``, a note ('' when none),
    and the image term built to decide (None when none was built or the start is not its field): the first solve
    from that field takes it rather than build its twin (0.05 s on a 40 x 25.6 mm 15 MHz frame; the decision's
    own warps 0.015 s).

    For a :class:`Previous`, its field unless the SSD image term (eq:IR; ``term_for()`` builds it on ``mesh``)
    is at zero at most its value at the field, over the pixels that the field keeps inside the moving image: a
    nearly still frame after a moving one, whose start one increment off holds Gauss-Newton in a neighbouring
    RF period (in vivo-like 15 MHz loop, 0.01 % after 0.62 %: 20 iterations, the data term falling 0.7 % an
    iteration, 20x its value at the fresh start's solution, and the result then set to zero by the check);
    the fresh start there converged in 3.  Anything else is returned as is."""
    if not isinstance(initial, Previous):
        return initial, "", None
    u = nodal_values(initial.u, mesh, "initial")
    term = term_for()
    keep = term.w * ~term.outside_mask(u)          # the pixels the start keeps; both starts judged on them
    psi_prev, psi_zero = (float(np.dot(keep * r, r)) for r in (term.residual(v) for v in (u, np.zeros_like(u))))
    if psi_prev < psi_zero:
        return u, "", term
    return initial.fresh, (f"{FRESH_NOTE}: the frames match better with no motion than with the previous "
                           f"increment (image term {psi_zero / psi_prev:.2g} of its value there)"), None


def _matched_images(ref, mov, I1, I2, mesh, spacing, origin, offset):
    """The two images the guess compares: the frames, or on a sequence both sampled at x + S(x)."""
    if offset is None:
        return ref, mov
    x, y = pixel_axes(ref.shape, spacing, origin)
    X, Y = np.meshgrid(x, y, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    Sg = displacement_at(offset, mesh, pts, "offset")
    return I1(pts + Sg).reshape(ref.shape), I2(pts + Sg).reshape(ref.shape)


def initial_guess(initial, ref, mov, I1, I2, mesh, spacing, origin, reg_factory, *, alpha, regularizer,
                  strategy="auto", offset=None, stats=None, settings=None, element_size=None, margin=None,
                  maxiter=20, tol=1e-3, linear_solver="auto", blockmatch_options=None,
                  coarse_to_fine="auto", rectangle=None, search: PyramidSearch | None = None) -> InitialGuess:
    """u_1 on ``mesh`` for ``initial`` (a name of :data:`INITIAL_NAMES`, a callable, a nodal vector, a
    RegistrationResult or a BlockMatchResult; see :func:`femreg.register`).  ``ref``/``mov``: the normalised
    frames, ``I1``/``I2`` their splines; ``stats``/``settings``: the speckle statistics and pyramid settings of
    the mesh stage, if it computed them.  ``rectangle`` (row slice, column slice): the pyramid runs on this part
    of the frames only (a scan-converted fan's largest rectangle without fill, whose fixed edges would pull its
    search to zero), its field extended as constant beyond it (:func:`femreg.pyramid.field_at`) for the final
    solve to correct.  ``search``: :func:`start_search`'s result on these arguments, if already computed."""
    if not isinstance(initial, str):
        bm = initial if isinstance(initial, BlockMatchResult) else None
        return InitialGuess(nodal_values(initial, mesh, "initial"), blockmatch=bm, stats=stats, settings=settings)
    if initial == "zero":
        return InitialGuess(np.zeros(2 * mesh.p.shape[1]), stats=stats, settings=settings)
    if initial == "blockmatch":
        a, b = _matched_images(ref, mov, I1, I2, mesh, spacing, origin, offset)
        coarse = strategy == "paper" and offset is None
        pg = paper_initial_guess(a, b, I1, I2, mesh, spacing, origin, reg_factory,
                                 blockmatch_options=blockmatch_options,
                                 coarse_pass=(lambda bm: wants_coarse_pass(coarse_to_fine, bm)) if coarse else False,
                                 element_size=element_size, margin=margin, maxiter=maxiter, tol=tol,
                                 linear_solver=linear_solver)
        return InitialGuess(pg.u0, blockmatch=pg.blockmatch, stats=stats, settings=settings, timings=pg.timings)
    if search is None:
        search = start_search(initial, ref, mov, I1, I2, mesh, spacing, origin, regularizer=regularizer, offset=offset,
                              stats=stats, settings=settings, element_size=element_size, rectangle=rectangle)
    guess = pyramid_solve(search, regularizer_factory=reg_factory, margin=margin, tol=tol, linear_solver=linear_solver)
    v = guess(mesh.p.T)
    u0 = np.empty(2 * len(v))
    u0[0::2], u0[1::2] = v[:, 0], v[:, 1]
    return InitialGuess(u0, blockmatch=guess.blockmatch, pyramid=guess, coarse_u0=u0.copy(), stats=search.stats,
                        settings=search.settings, timings={f"pyramid_{k}": v for k, v in guess.timings.items()})


def start_search(initial, ref, mov, I1, I2, mesh, spacing, origin, *, regularizer, offset=None, stats=None,
                 settings=None, element_size=None, rectangle=None) -> PyramidSearch | None:
    """The part of :func:`initial_guess` before any solve, whose block matching tells where the frames do not
    match (:func:`femreg.echo.unmatched_crop`): for ``initial="pyramid"`` the pyramid's envelopes, global and
    local search (:func:`femreg.pyramid.pyramid_search`), on ``rectangle`` (row slice, column slice) of the frames
    when given; None for the other starts (the paper's block matching comes with its coarse pass and solve).
    Arguments as :func:`initial_guess`'s; hand the result to it as ``search``."""
    if not (isinstance(initial, str) and initial == "pyramid"):
        return None
    a, b = _matched_images(ref, mov, I1, I2, mesh, spacing, origin, offset)
    env_a = None if (stats is None or offset is not None) else stats.envelope   # envelope of `a`
    if rectangle is not None:
        a, b = a[rectangle], b[rectangle]
        origin = np.asarray(origin, float) + np.array([rectangle[0].start, rectangle[1].start]) * np.asarray(spacing)
    if stats is None:
        stats, settings = image_settings(a, spacing, element_size, regularizer)
        env_a = stats.envelope
    return pyramid_search(a, b, spacing, origin, stats=stats, settings=settings, ref_envelope=env_a)
