"""Linear solvers for the symmetric positive (semi-)definite sparse systems of femreg: the Gauss-Newton step
``H du = -g`` of a registration (:mod:`femreg.solver`) and the forward and adjoint solves with K_II of the
modulus inversion (:mod:`femreg.inversion`).  One interface, :class:`SPDSolver`: ``factor(H)`` returns a factor
with ``solve(b)``; ``solve(H, b, reuse)`` factorises (or reuses the last factor) and solves.  A new method (a
sparse direct solver for 3D meshes, an iterative one) is one more branch of :meth:`SPDSolver.factor` returning
an object with ``solve``.

Methods (``method``):

* ``"cholesky"``: LAPACK banded Cholesky (``scipy.linalg.cholesky_banded``, dpbtrf) after a reverse
  Cuthill-McKee ordering (``scipy.sparse.csgraph``; Cuthill & McKee 1969, doi:10.1145/800195.805928) or another
  candidate order (the given node order; the caller's ``orderings``), whichever has the narrower band
  (:class:`BandedPattern`).  The ordering and the scatter of the matrix entries into the band are computed once
  per sparsity pattern and reused by every later factorisation (the lagged-diffusivity Hessian of the TV
  regularisers, and K(mu) of the inversion, change their values, not their pattern).
* ``"splu"``: SuperLU in symmetric mode (no pivoting, minimum-degree ordering of A^T + A, ``MMD_AT_PLUS_A``).
* ``"auto"`` (default): ``"cholesky"`` when the band holds at most :data:`BAND_LIMIT` entries, else ``"splu"``.
* ``"spsolve"``, ``"amg-cg"`` (pyamg smoothed aggregation + CG, given the rigid-body modes as ``B``).
* ``"sparse"``: a sparse direct factorisation for matrices that are not narrow-banded (3D meshes, whose band is
  ~(nodes across)^2): CHOLMOD's supernodal Cholesky (scikit-sparse, when installed; Chen et al., ACM TOMS 35
  (2008) 22, doi:10.1145/1391989.1391995), else SuperLU as ``"splu"``.  ``"pardiso"``: MKL PARDISO (pypardiso,
  when installed; about twice as fast as SuperLU on a 27 k-DOF hexahedral elasticity matrix, but not
  bit-reproducible run to run), else ``"sparse"``.  With ``large_method="pardiso"`` (volume registration) the
  ``"auto"`` rule sends systems whose band exceeds :data:`BAND_LIMIT` there instead of to SuperLU: the momentum
  Hessian of a 21 x 21 x 16 node hexahedral mesh (21 k unknowns, bandwidth 2714) factorised in 31 s banded,
  118 s SuperLU, 16 s PARDISO on the loaded 2-core machine; 16 x 16 x 12 nodes 5.8 / 16.3 / 6.1 s; 11 x 11 x 8
  0.5 / 1.3 / 1.4 s.

Memory: ``SPDSolver.release()`` drops the last factor; a PARDISO factor lives in MKL's memory and is freed there
(on release, when the next factorisation replaces it, or when it is collected), so a Gauss-Newton solve holds one
factor at a time.  A band ordering computes its bandwidth a block of columns at a time and builds the scatter
into the band only when it factorises (a pattern sent to a sparse direct solver never needs it).

The banded Cholesky factorises the paper geometry's Hessians faster than SuperLU at every mesh size tried
(timings: benchmarks/README.md).  A tiny diagonal shift (``shift``, relative to the mean diagonal; 1e-10 for
Gauss-Newton) keeps H definite when the images do not constrain some direction; if the banded Cholesky still meets
a non-positive pivot, that factorisation falls back to SuperLU.
"""
from __future__ import annotations

import contextlib
import functools

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

__all__ = ["SPDSolver", "BandedPattern", "BAND_LIMIT", "LINEAR_SOLVERS", "have_pardiso", "one_blas_thread",
           "single_blas_thread"]

#: Largest band (entries, (bandwidth + 1) * n) that ``method="auto"`` factorises with banded Cholesky:
#: 2.5e7 entries = 200 MB (a 0.5 mm mesh of the paper geometry needs 1.4e7).
BAND_LIMIT = 25_000_000

LINEAR_SOLVERS = ("auto", "cholesky", "splu", "spsolve", "amg-cg", "sparse", "pardiso")


class BandedPattern:
    """The band ordering of one sparsity pattern (CSC ``H``, symmetric) and the scatter of one triangle of its
    entries into LAPACK band storage.  ``orderings``: candidate permutations besides reverse Cuthill-McKee (tried
    first); the narrowest band wins (the first on ties).  ``upper``: store the upper triangle
    (``ab[b + i - j, j] = A_perm[i, j]``, i <= j), else the lower one (``ab[i - j, j]``, i >= j)."""

    def __init__(self, H: sp.csc_matrix, orderings=None, upper: bool = False):
        n = H.shape[0]
        self.indptr = H.indptr.copy()
        self.indices = H.indices.copy()
        # on a structured mesh the node numbering (or its rows / columns) is often narrower than RCM
        cands = [reverse_cuthill_mckee(sp.csr_matrix(H), symmetric_mode=True).astype(np.int64)]
        cands += [np.asarray(p, np.int64) for p in (orderings if orderings is not None else [np.arange(n)])]
        self.upper = bool(upper)
        self.n = n
        self._scatter = None
        if H.nnz <= BAND_CHUNK:         # small (2D) patterns: every candidate's indices at once, the scatter now
            # the candidates compared in 32-bit indices (a 2D pattern's are: several times faster than 64-bit
            # gathers), the winner's scatter in 64-bit
            it = np.int32 if n < 2 ** 31 - 1 else np.int64
            col = np.repeat(np.arange(n, dtype=it), np.diff(H.indptr))
            rows = H.indices.astype(it, copy=False)
            best = None
            for perm in cands:
                iperm = np.empty(n, dtype=it)
                iperm[perm] = np.arange(n, dtype=it)
                d = iperm[rows]
                d -= iperm[col]
                bw = max(int(d.max(initial=0)), -int(d.min(initial=0)))
                if best is None or bw < best[0]:
                    best = (bw, perm, iperm, int(d.max(initial=0)))
            bw, self.perm, iperm, lower = best
            self.bandwidth = bw if self.upper else lower
            iperm = iperm.astype(np.int64)
            self._scatter = self._scatter_of(iperm[H.indices], iperm[col])
            return
        # large (3D) patterns: the band widths a block of columns at a time; the scatter into the band is made on
        # the first factorisation, which a pattern too wide for "auto" (sent to a sparse direct solver) never has
        best = None
        for perm in cands:
            iperm = np.empty(n, dtype=np.int64)
            iperm[perm] = np.arange(n)
            bw, lower_bw = _band_widths(self.indptr, self.indices, iperm)
            if best is None or bw < best[0]:
                best = (bw, lower_bw, perm)
        bw, lower_bw, self.perm = best
        self.bandwidth = bw if self.upper else lower_bw

    def _scatter_of(self, i, j):
        """``(sel, flat)`` from the permuted row and column indices of every stored entry."""
        n, bw = self.n, self.bandwidth
        sel = i <= j if self.upper else i >= j
        flat = ((bw + i - j) * n + j)[sel] if self.upper else ((i - j) * n + j)[sel]
        return sel, flat

    def _band_scatter(self):
        """``(sel, flat)``: the entries of the stored triangle and their flat positions in the band array."""
        if self._scatter is None:
            n = self.n
            iperm = np.empty(n, dtype=np.int64)
            iperm[self.perm] = np.arange(n)
            self._scatter = self._scatter_of(iperm[self.indices], iperm[np.repeat(np.arange(n), np.diff(self.indptr))])
        return self._scatter

    @property
    def sel(self) -> np.ndarray:
        return self._band_scatter()[0]

    @property
    def flat(self) -> np.ndarray:
        return self._band_scatter()[1]

    def matches(self, H) -> bool:
        return (H.shape[0] == self.n and np.array_equal(H.indptr, self.indptr)
                and np.array_equal(H.indices, self.indices))

    @property
    def size(self) -> int:
        return (self.bandwidth + 1) * self.n

    def factor(self, data, shift: float = 0.0) -> "BandedFactor":
        """Cholesky factor of the matrix with CSC values ``data`` (this pattern's order) plus ``shift`` on the
        diagonal; raises ``numpy.linalg.LinAlgError`` when it is not positive definite."""
        sel, flat = self._band_scatter()
        ab = np.zeros((self.bandwidth + 1) * self.n)
        ab[flat] = data[sel]
        ab = ab.reshape(self.bandwidth + 1, self.n)
        if shift:
            ab[self.bandwidth if self.upper else 0] += shift
        cb = sla.cholesky_banded(ab, lower=not self.upper, overwrite_ab=True, check_finite=False)
        return BandedFactor(self, cb)


#: :meth:`BandedFactor.solve` with at least this many right-hand sides solves by blocks (level-3 BLAS) instead of
#: LAPACK's dpbtrs, whose band triangular solves (dtbsv) take one right-hand side at a time; rows per block at
#: least the bandwidth and at least BLOCKED_SOLVE_MIN_BLOCK.
BLOCKED_SOLVE_MIN_RHS = 16
BLOCKED_SOLVE_MIN_BLOCK = 64

#: Stored entries per pass of :func:`_band_widths` (its index arrays take 8 bytes per entry each).
BAND_CHUNK = 1 << 20


def _band_widths(indptr, indices, iperm):
    """``(max |i - j|, max (i - j))`` over the stored entries (row ``indices``, column from ``indptr``) of a CSC
    pattern under the permutation ``iperm`` (new index of each old one); a block of columns at a time, so that
    the permuted indices of a large pattern never exist all at once."""
    n = indptr.size - 1
    bw = lower = 0
    c0 = 0
    while c0 < n:
        c1 = int(np.searchsorted(indptr, indptr[c0] + BAND_CHUNK, side="right")) - 1
        c1 = min(n, max(c1, c0 + 1))
        a, b = int(indptr[c0]), int(indptr[c1])
        if b > a:
            d = iperm[indices[a:b]] - np.repeat(iperm[c0:c1], np.diff(indptr[c0:c1 + 1]))
            bw = max(bw, int(np.max(np.abs(d))))
            lower = max(lower, int(np.max(d)))
        c0 = c1
    return bw, lower


class BandedFactor:
    """A banded Cholesky factor of :class:`BandedPattern`; ``solve(b)`` in the original order."""

    method = "cholesky"

    def __init__(self, pattern: BandedPattern, cb):
        self.pattern, self.cb = pattern, cb
        self._blocks = None

    def solve(self, b):
        perm = self.pattern.perm
        b = np.asarray(b, float)[perm]
        if b.ndim == 2 and b.shape[1] >= BLOCKED_SOLVE_MIN_RHS:
            y = self._blocked_solve(b)
        else:
            y = sla.cho_solve_banded((self.cb, not self.pattern.upper), b, check_finite=False)
        x = np.empty_like(y)
        x[perm] = y
        return x

    def _upper_blocks(self):
        """The factor U (A = U^T U) as dense row blocks of ``nb`` >= bandwidth rows: per block (r0, r1, D), D = U[r0:r1,
        r0:min(r1 + nb, n)], the diagonal block and the coupling to the next block (none further: nb >= band)."""
        if self._blocks is None:
            cb, upper = self.cb, self.pattern.upper
            w, n = cb.shape[0] - 1, cb.shape[1]
            nb = max(w, BLOCKED_SOLVE_MIN_BLOCK)
            out = []
            for r0 in range(0, n, nb):
                r1 = min(r0 + nb, n)
                c1 = min(r1 + nb, n)
                D = np.zeros((r1 - r0, c1 - r0))
                for d in range(w + 1):            # the d-th superdiagonal U[i, i + d], i in [r0, r1)
                    i1 = min(r1, c1 - d)
                    if i1 <= r0:
                        continue
                    i = np.arange(r0, i1)
                    # upper storage: U[j - d, j] = cb[w - d, j]; lower: L[i + d, i] = U[i, i + d] = cb[d, i]
                    D[i - r0, i + d - r0] = cb[w - d, i + d] if upper else cb[d, i]
                out.append((r0, r1, D))
            self._blocks = out
        return self._blocks

    def _blocked_solve(self, b):
        """U^T U x = b by block forward and back substitution (level-3 BLAS: triangular solves and matrix products
        on row blocks), for many right-hand sides; the same arithmetic as LAPACK's dpbtrs up to rounding, several
        times faster (dpbtrs solves one right-hand side at a time)."""
        blocks = self._upper_blocks()
        y = np.array(b, float, order="C", copy=True)
        prev = None
        for r0, r1, D in blocks:                  # U^T y = b
            if prev is not None:
                p0, p1, P = prev
                y[r0:r1] -= P[:, p1 - p0:p1 - p0 + r1 - r0].T @ y[p0:p1]
            y[r0:r1] = sla.solve_triangular(D[:, :r1 - r0], y[r0:r1], trans="T", lower=False, check_finite=False)
            prev = (r0, r1, D)
        nxt = None
        for r0, r1, D in reversed(blocks):        # U x = y
            if nxt is not None:
                q0, q1 = nxt
                y[r0:r1] -= D[:, r1 - r0:r1 - r0 + q1 - q0] @ y[q0:q1]
            y[r0:r1] = sla.solve_triangular(D[:, :r1 - r0], y[r0:r1], lower=False, check_finite=False)
            nxt = (r0, r1)
        return y


class _SuperLUFactor:
    method = "splu"

    def __init__(self, lu):
        self.lu = lu

    def solve(self, b):
        return self.lu.solve(b)


class _CholmodFactor:
    method = "cholmod"

    def __init__(self, f):
        self.f = f

    def solve(self, b):
        return self.f(np.asarray(b, float))


class _PardisoFactor:
    """pypardiso's solver for one SPD matrix (type 2, upper triangle); solves reuse its factorisation.

    MKL keeps the factor in its own memory, which pypardiso frees only on request: :meth:`release` (also called
    when the factor is collected) hands it back.  Without it every Gauss-Newton iteration of a volume
    registration left its factor behind (about 0.3 GB each on the paper phantom's 2 mm mesh)."""

    method = "pardiso"

    def __init__(self, solver, A):
        self.solver, self.A = solver, A

    def solve(self, b):
        return self.solver.solve(self.A, np.asarray(b, float))

    def release(self):
        """Free MKL's memory of this factor (idempotent; the factor cannot solve afterwards)."""
        solver, self.solver = self.solver, None
        if solver is not None:
            with contextlib.suppress(Exception):        # never raise from a collector
                solver.free_memory(everything=True)

    def __del__(self):
        self.release()


def _sparse_direct(H, shift: float, splu, pardiso: bool = False):
    """Factor of the sparse SPD ``H`` (CSC, canonical) plus ``shift`` on the diagonal: PARDISO (``pardiso``, when
    pypardiso imports), CHOLMOD (scikit-sparse, when it imports), else ``splu(H)``."""
    if pardiso:
        try:
            import pypardiso
        except ImportError:
            pypardiso = None
        if pypardiso is not None:
            A = _upper_csr(H, shift)
            # pypardiso keeps a copy of A (to know a factored matrix again) below size_limit_storage entries and
            # a hash above: the hash, as this factor only ever solves with its own A
            solver = pypardiso.PyPardisoSolver(size_limit_storage=0)
            solver.set_matrix_type(2)
            solver.factorize(A)
            return _PardisoFactor(solver, A)
    try:
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky
    except ImportError:
        return splu(H)
    try:
        return _CholmodFactor(cholesky(H, beta=shift))
    except CholmodNotPositiveDefiniteError:
        return splu(H)


def _upper_csr(H, shift: float = 0.0) -> sp.csr_matrix:
    """The upper triangle (diagonal included) of the symmetric CSC ``H`` plus ``shift`` on the diagonal, as CSR
    with sorted indices (PARDISO's input for a symmetric matrix).  H's CSC arrays are also its CSR ones (H is
    symmetric), so the triangle is a selection of them, without the sums and conversions of ``sp.triu``."""
    H = sp.csc_matrix(H)
    if not H.has_sorted_indices or not H.has_canonical_format:
        H = H.copy()
        H.sum_duplicates()
    n = H.shape[0]
    counts = np.diff(H.indptr)
    keep = np.empty(H.nnz, bool)
    kept = np.zeros(n, dtype=np.int64)
    step = max(1, n // 16)
    for r0 in range(0, n, step):                # blocks of rows: no nnz-sized index array
        r1 = min(n, r0 + step)
        a, b = H.indptr[r0], H.indptr[r1]
        k = keep[a:b]
        k[...] = H.indices[a:b] >= np.repeat(np.arange(r0, r1, dtype=H.indices.dtype), counts[r0:r1])
        kept[r0:r1] = np.diff(np.concatenate(([0], np.cumsum(k)))[H.indptr[r0:r1 + 1] - a])
    indptr = np.zeros(n + 1, dtype=H.indptr.dtype)
    np.cumsum(kept, out=indptr[1:])
    A = sp.csr_matrix((H.data[keep], H.indices[keep], indptr), shape=H.shape)
    if shift:
        d = A.indptr[:-1]                      # sorted: each row's first kept entry is its diagonal
        if not np.array_equal(A.indices[d[counts > 0]], np.flatnonzero(counts > 0)) or not (counts > 0).all():
            return sp.triu(H + shift * sp.identity(n, format="csc"), format="csr")
        A.data[d] += shift
    return A


def have_pardiso() -> bool:
    """Whether pypardiso (MKL PARDISO) is importable."""
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return False
    return True


_BLAS = None


def one_blas_thread():
    """Context in which BLAS/LAPACK run on one thread (threadpoolctl; a no-op without it).

    The banded factorisations here are small (bandwidth ~50-200): extra BLAS threads only synchronise, and on a
    busy machine OpenBLAS's waiting threads made them several times slower."""
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
    BLAS threads cost more than they give on a shared machine)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)
    return wrapper


class SPDSolver:
    """Solve H x = b for symmetric positive (semi-)definite sparse H (see the module docstring for ``method``).

    ``factor(H)`` returns a factor with ``solve(b)``; ``solve(H, b, reuse=True)`` reuses the last factorisation
    if H is the same object as last time.  ``shift``: diagonal shift relative to the mean ``|diagonal|``;
    ``orderings``, ``upper``: candidate orders and storage of the banded Cholesky (:class:`BandedPattern`);
    ``one_thread``: run the banded factorisation and solves on one BLAS thread (:func:`one_blas_thread`)."""

    def __init__(self, method: str = "auto", shift: float = 1e-10, permc_spec: str = "MMD_AT_PLUS_A", B=None,
                 band_limit: int = BAND_LIMIT, orderings=None, upper: bool = False, one_thread: bool = True,
                 large_method: str = "splu"):
        if method not in LINEAR_SOLVERS:
            raise ValueError(f"unknown linear solver {method!r}; choose one of {', '.join(LINEAR_SOLVERS)}")
        self.permc_spec = permc_spec
        self.B = B  # near-null-space (rigid-body modes) for pyamg
        self.method = method
        self.shift = shift
        self.band_limit = int(band_limit)
        self.orderings = orderings
        self.upper = upper
        self.one_thread = one_thread
        if large_method not in ("splu", "pardiso"):
            raise ValueError(f"large_method must be 'splu' or 'pardiso', got {large_method!r}")
        #: where ``"auto"`` sends systems whose band exceeds ``band_limit``: "splu", or "pardiso" (when installed,
        #: else the "sparse" branch)
        self.large_method = large_method
        self._key = None
        self._fact = None
        self._pattern = None
        self.n_factorizations = 0
        #: method used by the last factorisation ("cholesky" or "splu" for auto/cholesky)
        self.last_method = None

    def _shift_value(self, H) -> float:
        if not self.shift:
            return 0.0
        return self.shift * (float(np.mean(np.abs(H.diagonal()))) or 1.0)

    def _shifted(self, H):
        H = sp.csc_matrix(H)
        return H + self._shift_value(H) * sp.identity(H.shape[0], format="csc")

    def _splu(self, H):
        # H is SPD: symmetric mode (no pivoting, ordering of A^T + A) keeps the factor sparse, faster than
        # the default LU.  (MKL PARDISO was not faster here and is not bit-reproducible run to run.)
        return _SuperLUFactor(spla.splu(self._shifted(H), permc_spec=self.permc_spec, diag_pivot_thresh=0.0,
                                        options=dict(SymmetricMode=True)))

    def _threads(self):
        return one_blas_thread() if self.one_thread else contextlib.nullcontext()

    def factor(self, H):
        """A factor of ``H`` (``solve(b)``, ``method``) for the direct methods ("auto", "cholesky", "splu",
        "sparse", "pardiso")."""
        if self.method in ("auto", "cholesky"):
            H = sp.csc_matrix(H)
            if not H.has_canonical_format:
                H = H.copy()
                H.sum_duplicates()
            if self._pattern is None or not self._pattern.matches(H):
                self._pattern = BandedPattern(H, self.orderings, self.upper)
            pat = self._pattern
            if self.method == "cholesky" or pat.size <= self.band_limit:
                try:
                    with self._threads():
                        return pat.factor(H.data, self._shift_value(H))
                except np.linalg.LinAlgError:
                    pass  # a non-positive pivot (semi-definite H): SuperLU without pivoting carries on
            else:
                if self.large_method == "pardiso":
                    return _sparse_direct(H, self._shift_value(H), self._splu, pardiso=True)
        if self.method in ("sparse", "pardiso"):
            H = sp.csc_matrix(H)
            return _sparse_direct(H, self._shift_value(H), self._splu, pardiso=self.method == "pardiso")
        return self._splu(H)

    def release(self):
        """Drop the last factorisation (MKL's memory of a PARDISO factor is freed at once)."""
        fact, self._fact, self._key = self._fact, None, None
        if hasattr(fact, "release"):
            fact.release()

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
            self.release()              # the old factor goes before the new one is made (they never coexist)
            self._fact = self.factor(H)
            self.last_method = self._fact.method
            self._key = H
            self.n_factorizations += 1
        if self._fact.method == "cholesky":
            with self._threads():
                return self._fact.solve(np.asarray(b, float))
        return self._fact.solve(b)
