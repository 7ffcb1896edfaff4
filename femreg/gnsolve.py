"""The solve stage of :func:`femreg.register`: one Gauss-Newton solve of eq:objf on one mesh -- the SSD image term
(eq:IR with the fixed reference gradient, eq:wfnew; :class:`femreg.data_term.SSDTerm`) over the pixel centres
inside the mesh, plus a fresh regulariser weighted per 2 x 2 mm element (:mod:`femreg.scaling`), minimised by
:func:`femreg.solver.gauss_newton`.  The initial-guess stages (the pyramid's envelope level, the paper's coarse
pass) and the repairs call it too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .data_term import SSDTerm
from .errors import InputError
from .fields import element_strain_operator
from .pixels import PixelQuadrature, PointLocator
from .regularizers import Regularizer
from .result import displacement_at
from .scaling import effective_alpha
from .solver import GN_ENERGY_TOL, Objective, gauss_newton

__all__ = ["Solve", "image_term", "solve"]


@dataclass
class Solve:
    """One Gauss-Newton solve on one mesh (plain data passed between the stages)."""

    mesh: object
    u: np.ndarray
    gn: object
    data: SSDTerm
    locator: PointLocator
    reg: Regularizer
    start: np.ndarray
    psi_start: float              # data term at ``start`` (the first evaluation of the solve, cached there)


def image_term(I1, I2, mesh, shape, spacing, origin, *, offset=None, locator=None) -> SSDTerm:
    """The SSD image term (eq:IR, fixed reference gradient eq:wfnew) of :func:`femreg.register` on ``mesh``:
    pixel-centre quadrature over the reference grid ``shape``/``spacing``/``origin`` (mm), both images sampled at
    x + S(x) with ``offset`` S (callable, nodal vector or result; None = 0).  Pixels where ``I1.weights_mask``
    (if set) is False get weight 0 (the fill of a scan-converted fan)."""
    quad = PixelQuadrature(mesh, shape, spacing, origin, locator=locator or PointLocator(mesh))
    if quad.n_pixels == 0:
        raise InputError("mesh outside the image: no pixel centre lies inside the mesh")
    S = None if offset is None else displacement_at(offset, mesh, quad.points, "offset")
    term = SSDTerm(quad, I1, I2, offset=S)
    keep = getattr(I1, "weights_mask", None)      # a fan's fill and its neighbourhood (femreg.echo.fan_weights)
    if keep is not None:
        term.w = np.where(keep.ravel()[quad.index], term.w, 0.0)
        term.fan_keep = keep.ravel()[quad.index]      # femreg.repair.element_ncc: quality over the fan only
    return term


def solve(I1, I2, mesh, shape, spacing, origin, reg_factory, u0, *, offset=None, locator=None, maxiter=20,
          tol=1e-3, linear_solver="auto", callback=None, mask_outside=False, strain_tol=None, term=None) -> Solve:
    """Gauss-Newton stage: SSD term (eq:wfnew) on ``mesh`` + a fresh regulariser with alpha per 2 x 2 mm element.

    ``mask_outside``: pixels that the start ``u0`` maps outside the moving image (less than 2 pixels from its
    edge) get weight 0 -- the moving image holds nothing to compare them with (large motion), and its zero
    outside would pull their elements; the regulariser carries the field there.  ``term``: an image term built by
    the caller instead (the samples of a beam frame, :class:`femreg.geometry.BeamSSDTerm`)."""
    locator = locator or PointLocator(mesh)
    data = term if term is not None else image_term(I1, I2, mesh, shape, spacing, origin, offset=offset,
                                                    locator=locator)
    if mask_outside:
        out = data.outside_mask(u0)
        if out.any() and not out.all():
            data.w = np.where(out, 0.0, data.w)
    reg = reg_factory()
    reg.alpha = effective_alpha(reg.alpha, mesh)
    reg.setup(mesh)
    psi_start = data.energy(u0)              # gauss_newton's first evaluation then comes from the cache
    gn = gauss_newton(Objective(data, reg), u0, maxiter=maxiter, tol=tol, linear_solver=linear_solver,
                      callback=callback, strain_tol=strain_tol,
                      energy_tol=None if strain_tol is None else GN_ENERGY_TOL,
                      strain_operator=None if strain_tol is None else element_strain_operator(mesh))
    return Solve(mesh=mesh, u=gn.x, gn=gn, data=data, locator=locator, reg=reg, start=u0, psi_start=psi_start)
