"""Gauss-Newton minimisation of pi = psi + R (eq:objf) with a backtracking safeguard.

Each iteration solves ``H du = -g`` (H = data Gauss-Newton Hessian of eq:wfnew + the regulariser's Hessian,
symmetric positive (semi-)definite), then tries ``u + du``; if the energy rises the step is halved (up to
``max_backtracks`` times).  Stop when ``||du|| / ||u|| < tol`` (the paper's rule, 1e-3) or after ``maxiter``
(20) iterations.  The best iterate seen is returned, never NaN.

Linear solver: the system is SPD and small.  Measured on the paper geometry (benchmarks/bench_register.py
--solvers, 2-core shared machine): 6.1 k DOF (1 mm mesh) SuperLU ``splu`` factorise + solve 0.03 s, later solves
with the stored factor 2 ms; ``spsolve`` 0.035 s every time; pyamg smoothed aggregation + CG (given the rigid-body
modes) 0.10 s set-up, 14 ms per solve.  23.7 k DOF (0.5 mm): splu 0.35 s then 19 ms; spsolve 0.37 s each;
pyamg 0.96 s then 0.23 s.  So ``splu`` (COLAMD ordering; MMD_AT_PLUS_A took 3.8 s) is the default, and when H
is constant (fixed-gradient data term of eq:wfnew + a quadratic regulariser) it is factorised ONCE and reused by
every iteration.  CHOLMOD (scikit-sparse) would need libsuitesparse-dev and a build; at these sizes the
factorisation is not the bottleneck (the cubic re-interpolation of I_2 is).  A tiny diagonal shift (1e-10 of
the mean diagonal) keeps H definite when the images do not constrain some direction
(e.g. a linear-intensity image seen through R_eps, which leaves a translation free).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["GaussNewtonResult", "gauss_newton", "Objective", "SPDSolver"]


class SPDSolver:
    """Solve H x = b for symmetric positive (semi-)definite sparse H; reuses the factorisation if H is the same
    object as last time (``reuse=True``)."""

    def __init__(self, method: str = "splu", shift: float = 1e-10, permc_spec: str = "MMD_AT_PLUS_A", B=None):
        self.permc_spec = permc_spec
        self.B = B  # near-null-space (rigid-body modes) for pyamg
        if method not in ("splu", "spsolve", "amg-cg"):
            raise ValueError(f"unknown linear solver {method!r}; choose 'splu', 'spsolve' or 'amg-cg'")
        self.method = method
        self.shift = shift
        self._key = None
        self._fact = None
        self.n_factorizations = 0

    def _shifted(self, H):
        H = sp.csc_matrix(H)
        d = H.diagonal()
        s = self.shift * (float(np.mean(np.abs(d))) or 1.0)
        return H + s * sp.identity(H.shape[0], format="csc")

    def solve(self, H, b, reuse: bool = False):
        if self.method == "spsolve":
            return spla.spsolve(self._shifted(H), b)
        if self.method == "amg-cg":
            import pyamg
            A = sp.csr_matrix(self._shifted(H))
            if not (reuse and self._key is H and self._fact is not None):
                self._fact = pyamg.smoothed_aggregation_solver(A, B=self.B, symmetry="symmetric")
                self._key = H
                self.n_factorizations += 1
            return self._fact.solve(b, tol=1e-10, accel="cg", maxiter=200)
        if not (reuse and self._key is H and self._fact is not None):
            # H is SPD: symmetric mode (no pivoting, ordering of A^T + A) keeps the factor sparse: 2-3x faster
            # than the default LU for the per-iteration refactorisation of TV regularisers.  (MKL PARDISO was
            # not faster here and is not bit-reproducible run to run.)
            self._fact = spla.splu(self._shifted(H), permc_spec=self.permc_spec, diag_pivot_thresh=0.0,
                                   options=dict(SymmetricMode=True))
            self._key = H
            self.n_factorizations += 1
        return self._fact.solve(b)


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

    def parts(self, u):
        return self.data.energy(u), self.reg.energy(u)

    def gradient(self, u):
        return self.data.gradient(u) + self.reg.gradient(u)

    def hessian(self, u):
        if self.hessian_constant and self._H is not None:
            return self._H
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
          3: "gradient is zero: the initial guess is already a stationary point"}


def gauss_newton(objective, u0, *, maxiter: int = 20, tol: float = 1e-3, max_backtracks: int = 8,
                 linear_solver: str = "splu", callback=None) -> GaussNewtonResult:
    """Minimise ``objective`` (energy/gradient/hessian, see :class:`Objective`) from ``u0``.

    Parameters
    ----------
    maxiter : int
        Maximum Gauss-Newton iterations (paper: 20).
    tol : float
        Stop when ``||du|| / ||u|| < tol`` (paper: 1e-3).
    max_backtracks : int
        Step halvings tried when the energy rises.
    linear_solver : {'splu', 'spsolve', 'amg-cg'}
    callback : callable(u, info_dict), optional
        Called after every iteration.
    """
    if int(maxiter) < 0:
        raise ValueError(f"maxiter must be >= 0, got {maxiter}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be > 0, got {tol}")
    solver = SPDSolver(linear_solver)
    u = np.array(u0, dtype=float, copy=True)
    if not np.all(np.isfinite(u)):
        raise ValueError("initial displacement contains NaN/Inf")
    E = float(objective.energy(u))
    if not np.isfinite(E):
        raise ValueError("energy of the initial guess is not finite")
    hist, steps, times = [E], [], []
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
        du = -solver.solve(H, g, reuse=getattr(objective, "hessian_constant", False))
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
    success = status in (0, 3)
    msg = STATUS[status]
    if status == 1:
        msg = f"maximum number of iterations ({int(maxiter)}) reached"
    return GaussNewtonResult(x=best_u, fun=best_E, success=success, status=status, message=msg, nit=nit,
                             energy_history=hist, step_history=steps, timings=times,
                             n_factorizations=solver.n_factorizations)
