"""The paper's initial guess (``strategy="paper"``, ``initial="blockmatch"``): NCC block matching of the two frames
(:func:`femreg.blockmatch.block_match`, 5 x 9 mm windows by default), interpolated to the nodes, and at large
strain a first registration on a 3x coarser mesh from that start (the coarse pass: 3D SI frames 1 -> 10, total
strain error 349 % -> 11 %).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .blockmatch import BlockMatchResult, block_match
from .gnsolve import solve
from .mesh import DEFAULT_ELEMENT_SIZE, roi_mesh
from .pyramid import field_at
from .result import nodal_values

__all__ = ["COARSE_TO_FINE_STRAIN", "PaperGuess", "paper_initial_guess", "wants_coarse_pass"]

#: Global strain of the block-matching field above which ``register`` adds a coarse pass (``coarse_to_fine``,
#: ``strategy="paper"``).
COARSE_TO_FINE_STRAIN = 0.01


@dataclass
class PaperGuess:
    """Output of :func:`paper_initial_guess`: the nodal start ``u0`` (2 n_nodes,) mm on the final mesh, the block
    matching, and the seconds of the coarse pass (``timings["coarse_pass"]``, when it ran)."""

    u0: np.ndarray
    blockmatch: BlockMatchResult
    timings: dict = field(default_factory=dict)


def wants_coarse_pass(coarse_to_fine, bm: BlockMatchResult) -> bool:
    """``coarse_to_fine`` True, or "auto" and the block matching's global strain above :data:`COARSE_TO_FINE_STRAIN`."""
    return coarse_to_fine is True or (coarse_to_fine == "auto" and bm.global_strain() > COARSE_TO_FINE_STRAIN)


def paper_initial_guess(a, b, I1, I2, mesh, spacing, origin, reg_factory, *, blockmatch_options=None,
                        coarse_pass=False, element_size=None, margin=None, maxiter=20, tol=1e-3,
                        linear_solver="auto") -> PaperGuess:
    """Block matching of ``a`` against ``b`` (the normalised frames, or both sampled at x + S on a sequence) at the
    nodes of ``mesh``; ``coarse_pass``: a callable ``(BlockMatchResult) -> bool`` (:func:`wants_coarse_pass`) or
    False.  The coarse pass registers ``I1``/``I2`` (:class:`femreg.image.SplineImage`) on a structured mesh of 3x
    ``element_size`` (default :data:`femreg.mesh.DEFAULT_ELEMENT_SIZE`) from the block-matching start; nodes of
    ``mesh`` beyond the coarse mesh keep the block-matching value."""
    bm = block_match(a, b, spacing, origin, **(blockmatch_options or {}))
    u0 = nodal_values(bm, mesh, "initial")
    timings = {}
    if coarse_pass and coarse_pass(bm):
        tc = time.perf_counter()
        hc = np.broadcast_to(np.asarray(DEFAULT_ELEMENT_SIZE if element_size is None else element_size, float), (2,))
        cmesh = roi_mesh(a.shape, spacing, origin, element_size=tuple(3.0 * hc), margin=margin)
        coarse = solve(I1, I2, cmesh, a.shape, spacing, origin, reg_factory, nodal_values(bm, cmesh, "initial"),
                       maxiter=maxiter, tol=tol, linear_solver=linear_solver)
        pts = mesh.p.T
        v = field_at(cmesh, coarse.u, pts, coarse.locator)
        inside = coarse.locator.locate(pts).inside
        v[~inside] = bm(pts[~inside])    # nodes beyond the coarse mesh keep the block-matching value
        u0 = np.empty(2 * len(v))
        u0[0::2], u0[1::2] = v[:, 0], v[:, 1]
        timings["coarse_pass"] = time.perf_counter() - tc
    return PaperGuess(u0=u0, blockmatch=bm, timings=timings)
