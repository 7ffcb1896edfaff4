"""Gauss-Newton minimisation of pi = psi + R (eq:objf) with a backtracking safeguard.

Each iteration solves ``H du = -g`` (H = data Gauss-Newton Hessian of eq:wfnew + the regulariser's Hessian,
symmetric positive (semi-)definite), then tries ``u + du``; if the energy rises the step is halved (up to
``max_backtracks`` times).  Stop when ``||du|| / ||u|| < tol`` (the paper's rule, 1e-3) or after ``maxiter``
(20) iterations.  The best iterate seen is returned, never NaN.

Linear solver (``linear_solver``): the system is SPD, sparse and small.

* ``"cholesky"``: LAPACK banded Cholesky (``scipy.linalg.cholesky_banded``, dpbtrf) after a reverse
  Cuthill-McKee ordering (``scipy.sparse.csgraph``; Cuthill & McKee 1969, doi:10.1145/800195.805928) or the
  given node order, whichever has the narrower band.  The
  ordering and the scatter of the matrix entries into the band are computed once per sparsity pattern and reused
  by every later factorisation (the lagged-diffusivity Hessian of the TV regularisers changes its values, not
  its pattern, each iteration).
* ``"splu"``: SuperLU in symmetric mode (no pivoting, minimum-degree ordering of A^T + A, ``MMD_AT_PLUS_A``).
* ``"auto"`` (default): ``"cholesky"`` when the band holds at most :data:`BAND_LIMIT` entries, else ``"splu"``.
* ``"spsolve"``, ``"amg-cg"`` (pyamg smoothed aggregation + CG, given the rigid-body modes as ``B``).

Measured on the paper geometry (3740 x 147 px, R_P_sigma Hessian, 2-core shared machine, one factorisation):
2 mm mesh (1.6 k DOF) cholesky 2 ms, splu 12-17 ms (COLAMD 25-37 ms); 1 mm (6.1 k DOF) 43 ms vs 124 ms;
0.5 mm (23.7 k DOF, band 586) 0.20 s vs 1.0 s (SuperLU's stored factor solves in 0.2 / 2 / 13 ms).  When H is
constant (fixed-gradient data term of eq:wfnew + a quadratic regulariser) it is factorised ONCE and reused by
every iteration.  A tiny diagonal shift (1e-10 of the mean diagonal) keeps H definite when the images do not
constrain some direction (e.g. a linear-intensity image seen through R_eps, which leaves a translation free); if
the banded Cholesky still meets a non-positive pivot, that factorisation falls back to SuperLU.
"""
from __future__ import annotations

import contextlib
import functools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

__all__ = ["GaussNewtonResult", "gauss_newton", "Objective", "SPDSolver", "BAND_LIMIT", "GN_STRAIN_TOL",
           "GN_STRAIN_TOL_TIGHT", "STRAIN_STEPS"]

#: Largest band (entries, (bandwidth + 1) * n) that ``linear_solver="auto"`` factorises with banded Cholesky:
#: 2.5e7 entries = 200 MB (a 0.5 mm mesh of the paper geometry needs 1.4e7).
BAND_LIMIT = 25_000_000

LINEAR_SOLVERS = ("auto", "cholesky", "splu", "spsolve", "amg-cg")


class _BandedPattern:
    """RCM ordering of one sparsity pattern and the scatter of its lower triangle into LAPACK lower band storage
    ``ab[i - j, j] = A_perm[i, j]`` (``A_perm = H[perm][:, perm]``)."""

    def __init__(self, H: sp.csc_matrix):
        n = H.shape[0]
        self.indptr = H.indptr.copy()
        self.indices = H.indices.copy()
        col = np.repeat(np.arange(n), np.diff(H.indptr))
        # RCM or the given order, whichever has the narrower band: on a structured mesh the node numbering is
        # often narrower (momentum Hessian of a 25 x 25 node mesh: 103 vs 169, a 1.8x faster factorisation)
        best = None
        for perm in (reverse_cuthill_mckee(sp.csr_matrix(H), symmetric_mode=True).astype(np.int64),
                     np.arange(n, dtype=np.int64)):
            iperm = np.empty(n, dtype=np.int64)
            iperm[perm] = np.arange(n)
            i, j = iperm[H.indices], iperm[col]
            bw = int(np.max(np.abs(i - j), initial=0))
            if best is None or bw < best[0]:
                best = (bw, perm, i, j)
        _, self.perm, i, j = best
        self.lower = i >= j
        self.bandwidth = int(np.max(i - j, initial=0))
        self.flat = ((i - j) * n + j)[self.lower]
        self.n = n

    def matches(self, H) -> bool:
        return (H.shape[0] == self.n and np.array_equal(H.indptr, self.indptr)
                and np.array_equal(H.indices, self.indices))

    @property
    def size(self) -> int:
        return (self.bandwidth + 1) * self.n

    def factor(self, H, shift: float):
        ab = np.zeros((self.bandwidth + 1) * self.n)
        ab[self.flat] = H.data[self.lower]
        ab = ab.reshape(self.bandwidth + 1, self.n)
        ab[0] += shift
        with one_blas_thread():
            return sla.cholesky_banded(ab, lower=True, overwrite_ab=True, check_finite=False)

    def solve(self, cb, b):
        with one_blas_thread():
            y = sla.cho_solve_banded((cb, True), b[self.perm], check_finite=False)
        x = np.empty_like(y)
        x[self.perm] = y
        return x


_BLAS = None


def one_blas_thread():
    """Context in which BLAS/LAPACK run on one thread (threadpoolctl; a no-op without it).

    The banded factorisations here are small (bandwidth ~50-200): extra BLAS threads only synchronise, and on a
    busy machine OpenBLAS's waiting threads made them 5-20x slower (paper-size pair 0.38 s -> 2.4 s with one
    other process running on 2 cores)."""
    global _BLAS
    if _BLAS is None:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS = ThreadpoolController()
        except ImportError:  # pragma: no cover - threadpoolctl is a dependency
            _BLAS = False
    if _BLAS is False:
        return contextlib.nullcontext()
    return _BLAS.limit(limits=1, user_api="blas")


def single_blas_thread(fn):
    """Decorator: run ``fn`` in :func:`one_blas_thread` (the registration's arrays are small or memory bound;
    BLAS threads cost more than they give: a paper-size pair 0.35 s on one thread, 0.8-2.9 s with two threads
    on a 2-core machine running one other process)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)
    return wrapper


class SPDSolver:
    """Solve H x = b for symmetric positive (semi-)definite sparse H (see the module docstring for ``method``);
    with ``reuse=True`` the factorisation is reused if H is the same object as last time."""

    def __init__(self, method: str = "auto", shift: float = 1e-10, permc_spec: str = "MMD_AT_PLUS_A", B=None,
                 band_limit: int = BAND_LIMIT):
        if method not in LINEAR_SOLVERS:
            raise ValueError(f"unknown linear solver {method!r}; choose one of {', '.join(LINEAR_SOLVERS)}")
        self.permc_spec = permc_spec
        self.B = B  # near-null-space (rigid-body modes) for pyamg
        self.method = method
        self.shift = shift
        self.band_limit = int(band_limit)
        self._key = None
        self._fact = None
        self._pattern = None
        self.n_factorizations = 0
        #: method used by the last factorisation ("cholesky" or "splu" for auto/cholesky)
        self.last_method = None

    def _shift_value(self, H) -> float:
        return self.shift * (float(np.mean(np.abs(H.diagonal()))) or 1.0)

    def _shifted(self, H):
        H = sp.csc_matrix(H)
        return H + self._shift_value(H) * sp.identity(H.shape[0], format="csc")

    def _splu(self, H):
        # H is SPD: symmetric mode (no pivoting, ordering of A^T + A) keeps the factor sparse: 2-3x faster than
        # the default LU.  (MKL PARDISO was not faster here and is not bit-reproducible run to run.)
        return spla.splu(self._shifted(H), permc_spec=self.permc_spec, diag_pivot_thresh=0.0,
                         options=dict(SymmetricMode=True))

    def _factor_direct(self, H):
        """("cholesky", (pattern, factor)) or ("splu", SuperLU) for the direct methods."""
        if self.method in ("auto", "cholesky"):
            H = sp.csc_matrix(H)
            if not H.has_canonical_format:
                H = H.copy()
                H.sum_duplicates()
            if self._pattern is None or not self._pattern.matches(H):
                self._pattern = _BandedPattern(H)
            pat = self._pattern
            if self.method == "cholesky" or pat.size <= self.band_limit:
                try:
                    return "cholesky", (pat, pat.factor(H, self._shift_value(H)))
                except np.linalg.LinAlgError:
                    pass  # a non-positive pivot (semi-definite H): SuperLU without pivoting carries on
        return "splu", self._splu(H)

    def solve(self, H, b, reuse: bool = False):
        if self.method == "spsolve":
            return spla.spsolve(self._shifted(H), b)
        if self.method == "amg-cg":
            from .optional import require

            pyamg = require("pyamg", feature="linear_solver='amg-cg'")
            A = sp.csr_matrix(self._shifted(H))
            if not (reuse and self._key is H and self._fact is not None):
                self._fact = pyamg.smoothed_aggregation_solver(A, B=self.B, symmetry="symmetric")
                self._key = H
                self.n_factorizations += 1
            return self._fact.solve(b, tol=1e-10, accel="cg", maxiter=200)
        if not (reuse and self._key is H and self._fact is not None):
            self.last_method, self._fact = self._factor_direct(H)
            self._key = H
            self.n_factorizations += 1
        if self.last_method == "cholesky":
            pat, cb = self._fact
            return pat.solve(cb, np.asarray(b, float))
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


def gauss_newton(objective, u0, *, maxiter: int = 20, tol: float = 1e-3, max_backtracks: int = 8,
                 linear_solver: str = "auto", callback=None, strain_operator=None,
                 strain_tol: float | None = None) -> GaussNewtonResult:
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
        if strain_tol is not None and strain_operator is not None:
            e = strain_operator @ u
            de = strain_operator @ (step * du)
            small = small + 1 if float(np.sqrt(np.mean(de * de))) < strain_tol * float(np.sqrt(np.mean(e * e))) else 0
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
