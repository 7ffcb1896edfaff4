"""Gauss-Newton minimisation of pi = psi + R (eq:objf) with a backtracking safeguard.

Each iteration solves ``H du = -g`` (H = data Gauss-Newton Hessian of eq:wfnew + the regulariser's Hessian,
symmetric positive (semi-)definite), then tries ``u + du``; if the energy rises the step is halved (up to
``max_backtracks`` times).  Stop when ``||du|| / ||u|| < tol`` (the paper's rule, 1e-3) or after ``maxiter``
(20) iterations.  The best iterate seen is returned, never NaN.

Linear solver (``linear_solver``): :class:`femreg.linsolve.SPDSolver` (banded Cholesky after reverse
Cuthill-McKee by default; SuperLU, spsolve, AMG-CG).  When H is constant (fixed-gradient data term of eq:wfnew +
a quadratic regulariser) it is factorised ONCE and reused by every iteration.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .linsolve import (BAND_LIMIT, LINEAR_SOLVERS, SPDSolver, one_blas_thread,  # noqa: F401  (also from here)
                       single_blas_thread)

__all__ = ["GaussNewtonResult", "gauss_newton", "Objective", "SPDSolver", "BAND_LIMIT", "GN_STRAIN_TOL",
           "GN_STRAIN_TOL_TIGHT", "STRAIN_STEPS", "GN_ENERGY_TOL"]


class Objective:
    """pi = psi + R (eq:objf) from a data term and a regulariser (both with energy/gradient/hessian).

    When the data Hessian is fixed (eq:wfnew) and the regulariser is quadratic (``reg.quadratic``), the total
    Hessian is built once and reused (``hessian_constant``)."""

    def __init__(self, data, reg):
        self.data = data
        self.reg = reg
        self.hessian_constant = bool(getattr(reg, "quadratic", False))
        self._H = None

    def energy(self, u):
        return self.data.energy(u) + self.reg.energy(u)

    def gradient(self, u):
        return self.data.gradient(u) + self.reg.gradient(u)

    def hessian(self, u):
        if self.hessian_constant and self._H is not None:
            return self._H
        if hasattr(self.reg, "hessian_plus") and getattr(self.data, "hessian_fixed", False):
            return self.reg.hessian_plus(u, self.data.hessian(u))    # one pass into a fixed pattern
        H = (self.data.hessian(u) + self.reg.hessian(u)).tocsc()
        if self.hessian_constant:
            self._H = H
        return H


@dataclass
class GaussNewtonResult:
    """OptimizeResult-like record: ``x`` (best iterate), ``fun``, ``success``, ``status``, ``message``, ``nit``,
    ``energy_history`` (energy after each accepted iterate, starting with the initial guess),
    ``step_history`` (||du|| / ||u|| per iteration), ``timings`` (s per iteration)."""

    x: np.ndarray
    fun: float
    success: bool
    status: int
    message: str
    nit: int
    energy_history: list = field(default_factory=list)
    step_history: list = field(default_factory=list)
    timings: list = field(default_factory=list)
    n_factorizations: int = 0

    def __getitem__(self, key):  # scipy-style access
        return getattr(self, key)


STATUS = {0: "converged: ||du|| / ||u|| < tol",
          1: "maximum number of iterations reached",
          2: "line search could not decrease the energy; returning the best iterate",
          3: "gradient is zero: the initial guess is already a stationary point",
          4: "converged: the last steps changed the strains by less than the strain tolerance"}

#: Second Gauss-Newton stopping rule of ``strategy="auto"`` (:func:`femreg.register`): stop once consecutive steps
#: (:data:`STRAIN_STEPS`) each change the element strains by less than this fraction of their RMS.  The strain is
#: what elastography reports (its error is 0.1-14 % on the robustness benchmark); the lagged-diffusivity TV
#: converges linearly (0.4-0.7 per iteration), and ``||du|| / ||u|| < tol`` on the lateral component took 6-9
#: iterations where the strain had stopped changing after 3-5.  Robustness benchmark, R_P_sigma total strain
#: error and iterations with 0.5 % -> 1.5 % (seeds 0 and 7): every pair within 0.1 point except 2 deg rotation
#: (0.23 -> 0.41 %, seed 0); inclusions 1-2 iterations fewer (15 MHz inclusion 12.35 % / 6 -> 12.25 % / 4).
GN_STRAIN_TOL = 0.015
#: The tight form of the same rule, for the solves that must settle further:
#:
#: - the quadratic regularisers (R_eps, R_eps_i): their Hessian is factorised once, so an iteration costs one warp,
#:   and at 1.5 % the study's alpha sweep chose another alpha for R_eps_i (0.42 -> 0.56) and its accumulated 3D
#:   total strain errors rose by 1.4-1.5 points;
#: - solves restarted from reseeded peak-hopping nodes, far from converged around them (bending 0.5 -> 5 % under
#:   the 5.5 MHz probe: 9.5 % at 1.5 %, 7.2 % at 0.5 %);
#: - the grid of :func:`femreg.autoalpha.choose_alpha`, whose rules compare the strains of neighbouring alphas,
#:   1-2 % of their RMS apart (at 1.5 % the synthetic test pair's choice moved from 0.013 to 0.13).
GN_STRAIN_TOL_TIGHT = 0.005
#: ... on this many consecutive steps: the lagged-diffusivity iteration is not monotone on rotated pairs (strain
#: changes 4.2, 0.95, 2.3, 1.8, 0.7 % on 3 deg + 1 % under a 12 MHz probe), and one small step stopped it at
#: 4.1 % total strain error where the converged result has 1.3 %.
STRAIN_STEPS = 2
#: ... and, for the image registrations of :func:`femreg.gnsolve.solve`, each of those steps must also lower the
#: energy by less than this fraction of it: on rotated pairs the strain change dips below 1.5 % while the energy
#: still falls by 6e-4 of itself per step (3 % + 3 deg, L12 probe, 30 x 30 mm: steps 5-6 changed the strains by
#: 1.3 and 0.25 % at 6.8e-4 and 6.4e-4, steps 8-9 by 0.6 and 0.3 % at 4.9e-5 and 1.7e-5; stopping at 6 left 0.80 %
#: total strain error after the refinement pass, at 9 0.46 %).  Rotation sweep (48 pairs): no pair worse by more
#: than 0.01 point, 3 deg L15 1.0 -> 0.4 %, 4 deg L15 3 % 1.6 -> 0.4 %; robustness benchmark within 0.08 point.
GN_ENERGY_TOL = 2e-4


def gauss_newton(objective, u0, *, maxiter: int = 20, tol: float = 1e-3, max_backtracks: int = 8,
                 linear_solver: str = "auto", callback=None, strain_operator=None,
                 strain_tol: float | None = None, energy_tol: float | None = None) -> GaussNewtonResult:
    """Minimise ``objective`` (energy/gradient/hessian, see :class:`Objective`) from ``u0``.

    Parameters
    ----------
    maxiter : int
        Maximum Gauss-Newton iterations (paper: 20).
    tol : float
        Stop when ``||du|| / ||u|| < tol`` (paper: 1e-3).
    max_backtracks : int
        Step halvings tried when the energy rises.
    linear_solver : {'auto', 'cholesky', 'splu', 'spsolve', 'amg-cg'}
        See the module docstring; ``"auto"`` is banded Cholesky unless the band is very large.
    callback : callable(u, info_dict), optional
        Called after every iteration.
    strain_operator, strain_tol : sparse (m, n) matrix and float, optional
        A second stopping rule: stop when :data:`STRAIN_STEPS` consecutive steps each change the strains
        ``strain_operator @ u`` by less than ``strain_tol`` of their size (RMS over the m entries); see
        :data:`GN_STRAIN_TOL`.
    energy_tol : float, optional
        With the strain rule: a step counts as small only if it also lowered the energy by less than
        ``energy_tol`` of its value (:data:`GN_ENERGY_TOL`); None = the strain change alone.
    """
    if int(maxiter) < 0:
        raise ValueError(f"maxiter must be >= 0, got {maxiter}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be > 0, got {tol}")
    # a string names the method; an SPDSolver (e.g. the volume path's, with large_method="pardiso") is used as is
    solver = linear_solver if isinstance(linear_solver, SPDSolver) else SPDSolver(linear_solver)
    u = np.array(u0, dtype=float, copy=True)
    if not np.all(np.isfinite(u)):
        raise ValueError("initial displacement contains NaN/Inf")
    E = float(objective.energy(u))
    if not np.isfinite(E):
        raise ValueError("energy of the initial guess is not finite")
    hist, steps, times = [E], [], []
    small = 0                       # consecutive steps below the strain tolerance
    best_u, best_E = u.copy(), E
    status = 1
    nit = 0
    for it in range(int(maxiter)):
        t0 = time.perf_counter()
        g = objective.gradient(u)
        if not np.any(g):
            status = 3
            break
        H = objective.hessian(u)
        reuse = getattr(objective, "hessian_constant", False)
        du = -solver.solve(H, g, reuse=reuse)
        if not reuse:           # the next iteration factorises anew: the matrix and its factor go before the warps
            del H
            solver.release()
        if not np.all(np.isfinite(du)):
            status = 2
            break
        step = 1.0
        accepted = False
        for _ in range(max_backtracks + 1):
            trial = u + step * du
            Et = float(objective.energy(trial))
            if np.isfinite(Et) and Et <= E:
                accepted = True
                break
            step *= 0.5
        nit += 1
        times.append(time.perf_counter() - t0)
        if not accepted:
            nu = float(np.linalg.norm(u))
            # a full step below the stopping tolerance that cannot lower the energy: round-off, converged
            status = 0 if nu > 0 and float(np.linalg.norm(du)) / nu < tol else 2
            steps.append(0.0)
            break
        u, E = trial, Et
        hist.append(E)
        if E <= best_E:
            best_u, best_E = u.copy(), E
        nu = float(np.linalg.norm(u))
        rel = float(np.linalg.norm(step * du)) / nu if nu > 0 else (0.0 if not np.any(du) else np.inf)
        steps.append(rel)
        if callback is not None:
            callback(u, {"nit": nit, "energy": E, "step": step, "rel_change": rel})
        if rel < tol:
            status = 0
            break
        if strain_tol is not None and strain_operator is not None:
            e = strain_operator @ u
            de = strain_operator @ (step * du)
            settled = float(np.sqrt(np.mean(de * de))) < strain_tol * float(np.sqrt(np.mean(e * e)))
            if energy_tol is not None:      # hist[-2]: the energy before this step
                settled = settled and hist[-2] - E < energy_tol * abs(E)
            small = small + 1 if settled else 0
            if small >= STRAIN_STEPS:
                status = 4
                break
    success = status in (0, 3, 4)
    msg = STATUS[status]
    if status == 1:
        msg = f"maximum number of iterations ({int(maxiter)}) reached"
    return GaussNewtonResult(x=best_u, fun=best_E, success=success, status=status, message=msg, nit=nit,
                             energy_history=hist, step_history=steps, timings=times,
                             n_factorizations=solver.n_factorizations)
