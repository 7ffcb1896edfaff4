"""Compiled inner loops of the image term (numba, optional): cubic B-spline prefilter and evaluation
(:mod:`femreg.image`), the fused displacement -> pixel -> I_2 warp and its transpose, the element-by-element and
the separable data Hessian (:mod:`femreg.data_term`), the lagged-diffusivity Hessian on a fixed pattern
(:mod:`femreg.regularizers.momentum`), the Newton walk of point location on logically structured meshes
(:mod:`femreg.pixels`); and of the stages around the solve: the analytic signal, the global search's window sums
and axial resampling (:mod:`femreg.pyramid`), the out-of-image mask and the result grids
(:mod:`femreg.registration`), the element NCC of the quality map and the envelope lags of the peak-hopping check
(:mod:`femreg.repair`).

Each loop has a numpy/scipy twin in the module that uses it (``map_coordinates``, sparse products, a vectorised
walk); the two agree to round-off and tests compare them with independent references.  Why compiled: the
re-interpolation of I_2 at every pixel is the inner loop of Gauss-Newton (0.55 M points per iteration on a
paper-size image), several times faster compiled than ``map_coordinates`` or any vectorised numpy gather (the
measured figures of every stage: benchmarks/README.md, "Timings").  All loops live in this one file so that
numba's on-disk cache (keyed on this file) is invalidated together when any of them changes.  The first use on a
machine compiles them (seconds, once); later processes load the cache.  Single-threaded, no fastmath: the same
input gives the same output bit for bit.

Switching them off: ``FEMREG_NUMBA=0`` in the environment (numba is then not even imported), or
:func:`set_compiled` / ``with compiled(False):`` in a process (which also sets the variable for the processes it
starts, e.g. batch workers).  Every branch that
calls a loop of this file tests :func:`use_compiled` at the time of the call.

How to add a kernel
-------------------
1. Write the numpy/scipy form first, in the module that needs it; it stays as the twin (and is what runs without
   numba), so keep it readable rather than fast.
2. Add the loop here with ``@_jit`` (``# pragma: no cover - compiled``), plain loops over contiguous float64 /
   int64 arrays, outputs passed in (``out``) where the caller owns the buffer; no fastmath, no parallel, no
   globals other than constants, so that the same input gives the same output bit for bit.
3. At the call site branch on ``_kernels.use_compiled()`` (never on ``HAVE_NUMBA`` or ``_numba`` directly), at the
   time of the call, not once at import or in a cache that outlives the switch.
4. Test it: the compiled loop against its twin (tests/test_fast_paths.py, both values of the switch), the twin
   against an independent reference (an analytic value, scipy, finite differences), and nothing in
   tests/test_compiled_switch.py may change (register and track stage by stage with the loops on and off).
5. Measure the stage it speeds up with benchmarks/bench_register.py or bench_track.py (``--no-compiled`` for the
   twin) and put the figures in benchmarks/README.md, "Timings", not in a comment; a kernel is worth its upkeep
   only where its stage takes a noticeable share of a registration.
"""
from __future__ import annotations

import contextlib
import os

import numpy as np

__all__ = ["HAVE_NUMBA", "use_compiled", "set_compiled", "compiled", "ENV_SWITCH", "cache_is_cold", "notify_cold_cache",
           "COLD_CACHE_MESSAGE"]

#: Environment variable that turns the compiled loops off for a whole process and the processes it starts
#: (batch workers, the CLI): ``FEMREG_NUMBA=0`` (also "false", "no", "off"); numba is then not even imported.
ENV_SWITCH = "FEMREG_NUMBA"
_OFF = ("0", "false", "no", "off")

_numba = None
if os.environ.get(ENV_SWITCH, "").strip().lower() not in _OFF:
    try:  # optional compiled kernels (see the module docstring)
        import numba as _numba
    except ImportError:  # pragma: no cover - exercised where numba is absent
        _numba = None

#: True when numba is importable (and not switched off by :data:`ENV_SWITCH`); False forces the numpy twins.
#: Set it with :func:`set_compiled` or :func:`compiled`.
HAVE_NUMBA = _numba is not None


#: One line said (through :func:`notify_cold_cache`'s callable) before the first compiled call of a process that
#: finds numba's on-disk cache of this file cold.
COLD_CACHE_MESSAGE = "compiling numerical kernels once (cached for later runs)..."
_notice = None


def use_compiled() -> bool:
    """Whether the compiled (numba) kernels are used now (numba importable and :data:`HAVE_NUMBA` True)."""
    on = _numba is not None and HAVE_NUMBA
    if on and _notice is not None:
        _tell_cold()
    return on


def notify_cold_cache(write) -> None:
    """Call ``write(COLD_CACHE_MESSAGE)`` once, at the first :func:`use_compiled` that finds the loops on, when
    :func:`cache_is_cold` (the command line passes a writer to stderr); None: no notice."""
    global _notice
    _notice = write


def _tell_cold() -> None:
    global _notice
    write, _notice = _notice, None
    if cache_is_cold():
        write(COLD_CACHE_MESSAGE)


def cache_is_cold() -> bool:
    """True when no loop of this file has an on-disk cache index at least as new as the file: the first run on a
    machine (or after this file changed), when the first registration compiles them (10-15 s).  A stat of
    each index file (under a millisecond); False without numba or with the cache off."""
    if _numba is None:
        return False
    try:
        stamp = os.stat(__file__).st_mtime
    except OSError:
        return False
    paths = [getattr(getattr(getattr(f, "_cache", None), "_cache_file", None), "_index_path", None)
             for f in globals().values() if hasattr(f, "py_func")]
    paths = [p for p in paths if p]
    if not paths:                   # no on-disk cache (not writable): every process compiles, nothing to say once
        return False
    for p in paths:
        try:
            if os.stat(p).st_mtime >= stamp:
                return False
        except OSError:
            continue
    return True


def set_compiled(enabled: bool) -> bool:
    """Turn the compiled loops on or off in this process and in the processes it starts from now on (batch
    workers, the CLI: :data:`ENV_SWITCH` is set too); on only takes effect where numba is importable.  Returns the
    previous setting.  Objects built before keep what they computed (e.g. the spline coefficients of a
    :class:`femreg.image.SplineImage`, which are equal either way)."""
    global HAVE_NUMBA
    previous = HAVE_NUMBA
    HAVE_NUMBA = bool(enabled)
    os.environ[ENV_SWITCH] = "1" if enabled else "0"
    return previous


@contextlib.contextmanager
def compiled(enabled: bool = True):
    """``with compiled(False): ...`` runs the block on the numpy twins (``True``: on the compiled loops where
    numba is importable) and restores the previous setting (and environment) afterwards."""
    env = os.environ.get(ENV_SWITCH)
    previous = set_compiled(enabled)
    try:
        yield use_compiled()
    finally:
        set_compiled(previous)
        if env is None:
            os.environ.pop(ENV_SWITCH, None)
        else:
            os.environ[ENV_SWITCH] = env


def _jit(fn):
    """numba.njit with an on-disk cache; the plain Python function (never called) without numba."""
    if _numba is None:
        return fn
    try:
        return _numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # pragma: no cover - no writable cache location: compile in every process instead
        return _numba.njit(cache=False, nogil=True)(fn)


_SIXTH = 1.0 / 6.0


@_jit
def _cubic_weights(t):  # pragma: no cover - compiled
    """The four cubic B-spline weights of the fractional offset t in [0, 1)."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s * _SIXTH          # products, not divisions: the divide unit limited the loop
    w3 = t3 * _SIXTH
    w1 = 2.0 / 3.0 - t2 + 0.5 * t3
    return w0, w1, 1.0 - w0 - w1 - w3, w3


@_jit
def cubic_point(c, xp, yp, hi0, hi1):  # pragma: no cover - compiled
    """One value of the interpolant at fractional pixel index (xp, yp); ``c`` the coefficients mirror-padded by 2
    on every side; 0 outside the pixel cells [-1/2, hi] (and for NaN)."""
    if not (xp >= -0.5 and xp <= hi0 and yp >= -0.5 and yp <= hi1):
        return 0.0
    fx = np.floor(xp)
    fy = np.floor(yp)
    i = int(fx) + 1
    j = int(fy) + 1
    a0, a1, a2, a3 = _cubic_weights(xp - fx)
    b0, b1, b2, b3 = _cubic_weights(yp - fy)
    return (a0 * (b0 * c[i, j] + b1 * c[i, j + 1] + b2 * c[i, j + 2] + b3 * c[i, j + 3])
            + a1 * (b0 * c[i + 1, j] + b1 * c[i + 1, j + 1] + b2 * c[i + 1, j + 2] + b3 * c[i + 1, j + 3])
            + a2 * (b0 * c[i + 2, j] + b1 * c[i + 2, j + 1] + b2 * c[i + 2, j + 2] + b3 * c[i + 2, j + 3])
            + a3 * (b0 * c[i + 3, j] + b1 * c[i + 3, j + 1] + b2 * c[i + 3, j + 2] + b3 * c[i + 3, j + 3]))


@_jit
def cubic_kernel(c, x, y, hi0, hi1, out):  # pragma: no cover - compiled
    for p in range(x.shape[0]):
        out[p] = cubic_point(c, x[p], y[p], hi0, hi1)
    return out


@_jit
def warp_grid(c, hi0, hi1, bx, by, bxr, byc, Ux, Uy, ei, X, ej, Y, isx, isy, sub, out):  # pragma: no cover
    """I_2 at base + u/spacing minus ``sub`` (I_1, for the residual; empty for I_2 alone) over an (nr x nc) pixel
    grid of a tensor mesh; the base index per pixel (bx, by), or, with those empty, bxr[r] and byc[q] per row and
    column; Ux, Uy nodal values on the node grid; pixel row r in element row ei[r] at reference
    X[r], column q in ej[q] at Y[q].  u is interpolated axially once per pixel row (to every node column), then
    laterally per pixel.  The values of :func:`cubic_point` bit for bit, computed a pixel row at a time in three
    branch-free passes (positions, weights, the 4 x 4 sums) that the compiler vectorises (faster than one point
    at a time)."""
    has_sub = sub.shape[0] > 0
    full = bx.shape[0] > 0
    nc = ej.shape[0]
    ny = Ux.shape[1]
    rx = np.empty(ny)
    ry = np.empty(ny)
    xs = np.empty(nc)
    ys = np.empty(nc)
    ok = np.empty(nc)
    II = np.empty(nc, np.int64)
    JJ = np.empty(nc, np.int64)
    A = np.empty((4, nc))
    B = np.empty((4, nc))
    ncol = c.shape[1]
    cf = c.ravel()
    for r in range(ei.shape[0]):
        a = ei[r]
        x = X[r]
        for b in range(ny):
            rx[b] = (1.0 - x) * Ux[a, b] + x * Ux[a + 1, b]
            ry[b] = (1.0 - x) * Uy[a, b] + x * Uy[a + 1, b]
        row = r * nc
        xr = 0.0 if full else bxr[r]
        for q in range(nc):
            b = ej[q]
            y = Y[q]
            ux = (1.0 - y) * rx[b] + y * rx[b + 1]
            uy = (1.0 - y) * ry[b] + y * ry[b + 1]
            if full:
                xp = bx[row + q] + ux * isx
                yp = by[row + q] + uy * isy
            else:
                xp = xr + ux * isx
                yp = byc[q] + uy * isy
            inside = xp >= -0.5 and xp <= hi0 and yp >= -0.5 and yp <= hi1
            ok[q] = 1.0 if inside else 0.0          # outside (and NaN): 0, evaluated at a safe index
            xs[q] = xp if inside else 0.0
            ys[q] = yp if inside else 0.0
        for q in range(nc):
            fx = np.floor(xs[q])
            fy = np.floor(ys[q])
            II[q] = int(fx) + 1
            JJ[q] = int(fy) + 1
            A[0, q], A[1, q], A[2, q], A[3, q] = _cubic_weights(xs[q] - fx)
            B[0, q], B[1, q], B[2, q], B[3, q] = _cubic_weights(ys[q] - fy)
        for q in range(nc):
            k = II[q] * ncol + JJ[q]
            b0 = B[0, q]
            b1 = B[1, q]
            b2 = B[2, q]
            b3 = B[3, q]
            v = (A[0, q] * (b0 * cf[k] + b1 * cf[k + 1] + b2 * cf[k + 2] + b3 * cf[k + 3])
                 + A[1, q] * (b0 * cf[k + ncol] + b1 * cf[k + ncol + 1] + b2 * cf[k + ncol + 2]
                              + b3 * cf[k + ncol + 3])
                 + A[2, q] * (b0 * cf[k + 2 * ncol] + b1 * cf[k + 2 * ncol + 1] + b2 * cf[k + 2 * ncol + 2]
                              + b3 * cf[k + 2 * ncol + 3])
                 + A[3, q] * (b0 * cf[k + 3 * ncol] + b1 * cf[k + 3 * ncol + 1] + b2 * cf[k + 3 * ncol + 2]
                              + b3 * cf[k + 3 * ncol + 3])) * ok[q]
            if has_sub:
                v -= sub[row + q]
            out[row + q] = v
    return out


@_jit
def outside_grid(bx, by, bxr, byc, Ux, Uy, ei, X, ej, Y, isx, isy, hi0, hi1, out):  # pragma: no cover - compiled
    """out[p] = True where base + u/spacing (as :func:`warp_grid`, the same two forms of the base) lies less
    than 1 pixel inside the first pixel centre or beyond ``hi`` (fractional index) on either axis."""
    full = bx.shape[0] > 0
    nc = ej.shape[0]
    for r in range(ei.shape[0]):
        a = ei[r]
        x = X[r]
        for q in range(nc):
            b = ej[q]
            y = Y[q]
            w00 = (1.0 - x) * (1.0 - y)
            w10 = x * (1.0 - y)
            w11 = x * y
            w01 = (1.0 - x) * y
            ux = w00 * Ux[a, b] + w10 * Ux[a + 1, b] + w11 * Ux[a + 1, b + 1] + w01 * Ux[a, b + 1]
            uy = w00 * Uy[a, b] + w10 * Uy[a + 1, b] + w11 * Uy[a + 1, b + 1] + w01 * Uy[a, b + 1]
            p = r * nc + q
            if full:
                ix = bx[p] + ux * isx
                iy = by[p] + uy * isy
            else:
                ix = bxr[r] + ux * isx
                iy = byc[q] + uy * isy
            out[p] = ix < 1.0 or ix > hi0 or iy < 1.0 or iy > hi1
    return out


@_jit
def gradient_grid(w, res, gx, gy, ei, X, ej, Y, Gx, Gy):  # pragma: no cover - compiled
    """Gx[node grid] += sum_p N(p) w_p r_p gx_p (and y): the transpose of the separable pixel interpolation
    (lateral hats summed along each pixel row, then spread to the row's two node rows)."""
    nc = ej.shape[0]
    ny = Gx.shape[1]
    lx = np.empty(ny)
    ly = np.empty(ny)
    for r in range(ei.shape[0]):
        a = ei[r]
        x = X[r]
        lx[:] = 0.0
        ly[:] = 0.0
        for q in range(nc):
            b = ej[q]
            y = Y[q]
            p = r * nc + q
            v = w[p] * res[p]
            vx = v * gx[p]
            vy = v * gy[p]
            lx[b] += (1.0 - y) * vx
            lx[b + 1] += y * vx
            ly[b] += (1.0 - y) * vy
            ly[b + 1] += y * vy
        for b in range(ny):
            Gx[a, b] += (1.0 - x) * lx[b]
            Gx[a + 1, b] += x * lx[b]
            Gy[a, b] += (1.0 - x) * ly[b]
            Gy[a + 1, b] += x * ly[b]


@_jit
def hessian_rows(w, gx, gy, fx, rseg, n_seg, nc):  # pragma: no cover - compiled
    """Axial segment sums ``T[p, a, s, c] = sum_{r in segment s} fx[p, r] G_a[r, c]`` of the separable data
    Hessian (G = (w gx^2, w gx gy, w gy^2) over an (nr x nc) pixel grid, ``rseg[r]`` the element row of pixel row
    r, rows of a segment consecutive): one pass instead of nine (rows x cols) products and reductions."""
    T = np.zeros((3, 3, n_seg, nc))
    for r in range(rseg.shape[0]):
        s = rseg[r]
        f0 = fx[0, r]
        f1 = fx[1, r]
        f2 = fx[2, r]
        for c in range(nc):
            p = r * nc + c
            g0 = w[p] * (gx[p] * gx[p])
            g1 = (w[p] * gx[p]) * gy[p]
            g2 = w[p] * (gy[p] * gy[p])
            T[0, 0, s, c] += f0 * g0
            T[1, 0, s, c] += f1 * g0
            T[2, 0, s, c] += f2 * g0
            T[0, 1, s, c] += f0 * g1
            T[1, 1, s, c] += f1 * g1
            T[2, 1, s, c] += f2 * g1
            T[0, 2, s, c] += f0 * g2
            T[1, 2, s, c] += f1 * g2
            T[2, 2, s, c] += f2 * g2
    return T


@_jit
def gram_into_pattern(Kp, Ki, Kd, KTp, KTi, KTd, d, Hp, Hi, base, marker, out):  # pragma: no cover - compiled
    """out = base + K^T diag(d) K on the fixed CSR pattern (Hp, Hi) (Gustavson's row-by-row product, numeric
    phase only: the pattern is known, so no symbolic pass and no new arrays); ``marker`` (n,) int scratch."""
    for i in range(Hp.shape[0] - 1):
        for p in range(Hp[i], Hp[i + 1]):
            marker[Hi[p]] = p
            out[p] = base[p]
        for a in range(KTp[i], KTp[i + 1]):
            k = KTi[a]
            v = KTd[a] * d[k]
            for b in range(Kp[k], Kp[k + 1]):
                out[marker[Ki[b]]] += v * Kd[b]
    return out


@_jit
def add_into_pattern(Ap, Ai, Ad, scale, Hp, Hi, marker, out):  # pragma: no cover - compiled
    """out += scale * A for a CSR matrix A whose pattern lies inside the CSR pattern (Hp, Hi)."""
    for i in range(Hp.shape[0] - 1):
        for p in range(Hp[i], Hp[i + 1]):
            marker[Hi[p]] = p
        for a in range(Ap[i], Ap[i + 1]):
            out[marker[Ai[a]]] += scale * Ad[a]
    return out


@_jit
def knot_gradient(c, r0, nr, c0, nc, dx2, dy2, gx, gy):  # pragma: no cover - compiled
    """Gradient of the cubic interpolant at the pixel centres of the block (r0:r0+nr, c0:c0+nc), raveled into
    gx, gy; ``c`` the coefficients mirror-padded by 2.  The same operations in the same order as the numpy
    form in :meth:`femreg.image.SplineImage.gradient_at_pixels` (bit-identical), in one pass instead of six:
    the lateral smoothing of each coefficient row is computed once and kept for the two output rows that use
    it (a ring of three rows)."""
    sy = np.empty((3, nc))             # lateral smoothing of coefficient rows a - 1, a, a + 1 (ring)
    sx = np.empty(nc + 2)
    for k in range(2):                 # rows r0 + 1, r0 + 2 of the padded array
        a = r0 + 1 + k
        for j in range(nc):
            b = c0 + 2 + j
            sy[k, j] = (c[a, b - 1] + 4.0 * c[a, b] + c[a, b + 1]) / 6.0
    for i in range(nr):
        a = r0 + 2 + i
        nxt = (i + 2) % 3
        for j in range(nc):
            b = c0 + 2 + j
            sy[nxt, j] = (c[a + 1, b - 1] + 4.0 * c[a + 1, b] + c[a + 1, b + 1]) / 6.0
        prv = i % 3
        for j in range(nc + 2):
            b = c0 + 1 + j
            sx[j] = (c[a - 1, b] + 4.0 * c[a, b] + c[a + 1, b]) / 6.0
        o = i * nc
        for j in range(nc):
            gx[o + j] = (sy[nxt, j] - sy[prv, j]) / dx2
            gy[o + j] = (sx[j + 2] - sx[j]) / dy2


@_jit
def group_ncc(groups, x, Y, n):  # pragma: no cover - compiled
    """NCC of ``x`` with each row of ``Y`` (k, m) within each group (``groups`` (m,) in 0 .. n - 1): group
    means, then centred sums, accumulated in index order as ``np.bincount`` does (the same values as the numpy
    form in :func:`femreg.repair._group_ncc`), one pass per moment for all k rows.  Returns (ncc (k, n), count
    (n,)); NaN where a group has no variance."""
    k, m = Y.shape
    cnt = np.zeros(n)
    sx = np.zeros(n)
    sy = np.zeros((k, n))
    for p in range(m):
        g = groups[p]
        cnt[g] += 1.0
        sx[g] += x[p]
        for i in range(k):
            sy[i, g] += Y[i, p]
    mx = sx / cnt
    my = sy / cnt
    sxx = np.zeros(n)
    sxy = np.zeros((k, n))
    syy = np.zeros((k, n))
    for p in range(m):
        g = groups[p]
        dx = x[p] - mx[g]
        sxx[g] += dx * dx
        for i in range(k):
            dy = Y[i, p] - my[i, g]
            sxy[i, g] += dx * dy
            syy[i, g] += dy * dy
    q = np.empty((k, n))
    for i in range(k):
        for g in range(n):
            d = np.sqrt(sxx[g] * syy[i, g])
            q[i, g] = sxy[i, g] / d if d != 0.0 else np.nan     # 0 / 0 (no variance), as numpy gives
    return q, cnt


@_jit
def block_energies(a, res, nc, edges, nb):  # pragma: no cover - compiled
    """Sums of a^2 and (res + a)^2 over the row blocks [edges[k], edges[k + 1]) (k < nb) of the (rows x nc)
    pixel block that ``a``, ``res`` (raveled) cover: (Qa, Qw), each (nb, nc).  The sums of ``np.add.reduceat``
    over the squared arrays (to round-off: reduceat groups the additions differently), without those arrays."""
    Qa = np.zeros((nb, nc))
    Qw = np.zeros((nb, nc))
    for k in range(nb):
        for r in range(edges[k], edges[k + 1]):
            for q in range(nc):
                p = r * nc + q
                w = res[p] + a[p]
                Qa[k, q] += a[p] * a[p]
                Qw[k, q] += w * w
    return Qa, Qw


@_jit
def box_sums(R, w0, w1, na, nl):  # pragma: no cover - compiled
    """Sums of ``R`` and ``R**2`` over every w0 x w1 window with top-left corner (d0, d1), d0 < na, d1 < nl:
    (S1, S2), each (na, nl), from the two integral images (built in one pass)."""
    n0, n1 = R.shape
    I1 = np.zeros((n0 + 1, n1 + 1))
    I2 = np.zeros((n0 + 1, n1 + 1))
    for i in range(n0):
        a = 0.0
        b = 0.0
        for j in range(n1):
            v = R[i, j]
            a += v
            b += v * v
            I1[i + 1, j + 1] = I1[i, j + 1] + a
            I2[i + 1, j + 1] = I2[i, j + 1] + b
    S1 = np.empty((na, nl))
    S2 = np.empty((na, nl))
    for i in range(na):
        for j in range(nl):
            S1[i, j] = I1[i + w0, j + w1] - I1[i, j + w1] - I1[i + w0, j] + I1[i, j]
            S2[i, j] = I2[i + w0, j + w1] - I2[i, j + w1] - I2[i + w0, j] + I2[i, j]
    return S1, S2


@_jit
def axial_resample(img, pos, out):  # pragma: no cover - compiled
    """``img`` at fractional row positions ``pos`` (every column), cubic convolution (Keys, a = -0.5), zero
    outside: the compiled twin of :func:`femreg.pyramid._axial_resample`."""
    n, m = img.shape
    for r in range(pos.shape[0]):
        i0 = int(np.floor(pos[r]))
        t = pos[r] - i0
        w = (((-0.5 * t + 1.0) * t - 0.5) * t, (1.5 * t - 2.5) * t * t + 1.0, ((-1.5 * t + 2.0) * t + 0.5) * t,
             (0.5 * t - 0.5) * t * t)
        for c in range(m):
            out[r, c] = 0.0
        for k in range(4):
            idx = i0 - 1 + k
            if idx >= 0 and idx < n:
                wk = w[k]
                for c in range(m):
                    out[r, c] += wk * img[idx, c]
    return out


@_jit
def block_ncc(a, b, rseg, cseg, n_rs, n_cs):  # pragma: no cover - compiled
    """NCC of ``a`` and ``b`` (an nr x nc pixel grid, C order) over each block (rseg[r], cseg[c]) of pixels:
    block means first, then the centred sums (the two-pass formula of :func:`femreg.repair.element_ncc`).
    Returns (ncc, count), each (n_rs, n_cs); NaN where a block has no variance."""
    nr, nc = rseg.shape[0], cseg.shape[0]
    cnt = np.zeros((n_rs, n_cs))
    sa = np.zeros((n_rs, n_cs))
    sb = np.zeros((n_rs, n_cs))
    for r in range(nr):
        s = rseg[r]
        for c in range(nc):
            t = cseg[c]
            p = r * nc + c
            cnt[s, t] += 1.0
            sa[s, t] += a[p]
            sb[s, t] += b[p]
    ma = sa / cnt
    mb = sb / cnt
    sab = np.zeros((n_rs, n_cs))
    saa = np.zeros((n_rs, n_cs))
    sbb = np.zeros((n_rs, n_cs))
    for r in range(nr):
        s = rseg[r]
        for c in range(nc):
            t = cseg[c]
            p = r * nc + c
            da = a[p] - ma[s, t]
            db = b[p] - mb[s, t]
            sab[s, t] += da * db
            saa[s, t] += da * da
            sbb[s, t] += db * db
    return sab / np.sqrt(saa * sbb), cnt


@_jit
def spline_coefficients(data, z):  # pragma: no cover - compiled
    """Cubic B-spline coefficients of an image (pole ``z`` = sqrt(3) - 2), mirror boundary, axis 0 then axis 1,
    mirror-extended by 2 on every side: ``out[2:-2, 2:-2]`` is ``scipy.ndimage.spline_filter(data, 3,
    mode="mirror")`` (the same recursions and initial values as scipy's ni_splines.c, each axis's lines run
    side by side instead of one at a time), the border the ``np.pad(.., 2, mode="reflect")`` of it.  Both axes
    at least 3 long."""
    n0, n1 = data.shape
    out = np.empty((n0 + 4, n1 + 4))
    c = out[2:n0 + 2, 2:n1 + 2]
    gain = (1.0 - z) * (1.0 - 1.0 / z)
    # axis 0: the lines are the columns, processed a row at a time
    for i in range(n0):
        for j in range(n1):
            c[i, j] = data[i, j] * gain
    zn = np.power(z, n0 - 1)
    for j in range(n1):
        c[0, j] = c[0, j] + zn * c[n0 - 1, j]
    zi = z
    for i in range(1, n0 - 1):
        for j in range(n1):
            c[0, j] += zi * (c[i, j] + zn * c[n0 - 1 - i, j])
        zi *= z
    for j in range(n1):
        c[0, j] /= 1 - zn * zn
    for i in range(1, n0):
        for j in range(n1):
            c[i, j] += z * c[i - 1, j]
    for j in range(n1):
        c[n0 - 1, j] = (z * c[n0 - 2, j] + c[n0 - 1, j]) * z / (z * z - 1)
    for i in range(n0 - 2, -1, -1):
        for j in range(n1):
            c[i, j] = z * (c[i + 1, j] - c[i, j])
    # axis 1: the lines are the rows, run in blocks of 8 side by side (each recursion is a chain of dependent
    # steps: 8 independent chains keep the floating-point units busy)
    zn = np.power(z, n1 - 1)
    nb = 8
    acc = np.empty(nb)
    for i0 in range(0, n0, nb):
        i1 = min(i0 + nb, n0)
        for i in range(i0, i1):
            for j in range(n1):
                c[i, j] *= gain
            acc[i - i0] = c[i, 0] + zn * c[i, n1 - 1]
        zi = z
        for j in range(1, n1 - 1):
            for i in range(i0, i1):
                acc[i - i0] += zi * (c[i, j] + zn * c[i, n1 - 1 - j])
            zi *= z
        for i in range(i0, i1):
            c[i, 0] = acc[i - i0] / (1 - zn * zn)
        for j in range(1, n1):
            for i in range(i0, i1):
                c[i, j] += z * c[i, j - 1]
        for i in range(i0, i1):
            c[i, n1 - 1] = (z * c[i, n1 - 2] + c[i, n1 - 1]) * z / (z * z - 1)
        for j in range(n1 - 2, -1, -1):
            for i in range(i0, i1):
                c[i, j] = z * (c[i, j + 1] - c[i, j])
    # mirror (whole-sample) extension by 2: out[1] = c[1], out[0] = c[2], likewise at the other ends
    for k in range(2):
        for j in range(n1):
            out[1 - k, j + 2] = c[k + 1, j]
            out[n0 + 2 + k, j + 2] = c[n0 - 2 - k, j]
    for i in range(n0 + 4):
        for k in range(2):
            out[i, 1 - k] = out[i, k + 3]
            out[i, n1 + 2 + k] = out[i, n1 - k]
    return out


@_jit
def grid_fields(Ux, Uy, ei, X, hx, ej, Y, hy, r0, c0, out):  # pragma: no cover - compiled
    """ux, uy, exx, eyy, exy of a bilinear field on a tensor mesh (node-grid values Ux, Uy) at an (nr x nc) grid
    of points (row r in element row ei[r] at reference X[r], element height hx[r]; column q likewise), written
    to ``out[k, r0 + r, c0 + q]`` (k in that order); the arithmetic of the separable numpy form in
    :mod:`femreg.registration` (lateral interpolation first, then axial)."""
    for r in range(ei.shape[0]):
        a = ei[r]
        x = X[r]
        for q in range(ej.shape[0]):
            b = ej[q]
            y = Y[q]
            # lateral: value and d/dy on node rows a and a + 1
            xa0, xa1 = Ux[a, b], Ux[a, b + 1]
            xb0, xb1 = Ux[a + 1, b], Ux[a + 1, b + 1]
            ya0, ya1 = Uy[a, b], Uy[a, b + 1]
            yb0, yb1 = Uy[a + 1, b], Uy[a + 1, b + 1]
            lxa = xa0 + (xa1 - xa0) * y
            lxb = xb0 + (xb1 - xb0) * y
            lya = ya0 + (ya1 - ya0) * y
            lyb = yb0 + (yb1 - yb0) * y
            dxa = (xa1 - xa0) / hy[q]
            dxb = (xb1 - xb0) / hy[q]
            dya = (ya1 - ya0) / hy[q]
            dyb = (yb1 - yb0) / hy[q]
            i = r0 + r
            j = c0 + q
            out[0, i, j] = lxa + (lxb - lxa) * x
            out[1, i, j] = lya + (lyb - lya) * x
            out[2, i, j] = (lxb - lxa) / hx[r]
            out[3, i, j] = dya + (dyb - dya) * x
            out[4, i, j] = 0.5 * ((dxa + (dxb - dxa) * x) + (lyb - lya) / hx[r])


@_jit
def grid_values(F, ei, X, ej, Y, r0, c0, out):  # pragma: no cover - compiled
    """Bilinear interpolation of nodal fields on a tensor mesh (``F`` (k, n_x nodes, n_y nodes)) at an (nr x nc)
    grid of points (as :func:`grid_fields`), written to ``out[k, r0 + r, c0 + q]``; the same arithmetic as the
    values of :func:`grid_fields` (lateral first, then axial), so both agree bit for bit.  The lateral values
    on the two node rows of an element row are computed once for all its pixel rows."""
    nk, nc = F.shape[0], ej.shape[0]
    LA = np.empty((nk, nc))
    LB = np.empty((nk, nc))
    last = -1
    for r in range(ei.shape[0]):
        a = ei[r]
        x = X[r]
        if a != last:
            for k in range(nk):
                for q in range(nc):
                    b = ej[q]
                    y = Y[q]
                    LA[k, q] = F[k, a, b] + (F[k, a, b + 1] - F[k, a, b]) * y
                    LB[k, q] = F[k, a + 1, b] + (F[k, a + 1, b + 1] - F[k, a + 1, b]) * y
            last = a
        for k in range(nk):
            for q in range(nc):
                la = LA[k, q]
                out[k, r0 + r, c0 + q] = la + (LB[k, q] - la) * x


@_jit
def decimating_filter(e, w, idx, axis):  # pragma: no cover - compiled
    """``out[o] = sum_k w[k] e[idx[o, k]]`` along ``axis`` (0 or 1) of a 2D array: a 1D correlation evaluated
    only at the kept output samples (``idx`` holds each one's input taps, boundary already folded in)."""
    n0, n1 = e.shape
    n_out, taps = idx.shape
    if axis == 0:
        out = np.zeros((n_out, n1))
        for o in range(n_out):
            for k in range(taps):
                wk = w[k]
                i = idx[o, k]
                for j in range(n1):
                    out[o, j] += wk * e[i, j]
    else:
        out = np.zeros((n0, n_out))
        for i in range(n0):
            for o in range(n_out):
                acc = 0.0
                for k in range(taps):
                    acc += w[k] * e[i, idx[o, k]]
                out[i, o] = acc
    return out


@_jit
def warp_nodes(c, hi0, hi1, bx, by, ux_n, uy_n, nodes, N, isx, isy, sub, out):  # pragma: no cover - compiled
    """I_2 at base + u/spacing minus ``sub`` (as :func:`warp_grid`), u from the four shape functions N of each
    pixel (any quad mesh)."""
    has_sub = sub.shape[0] > 0
    for p in range(bx.shape[0]):
        ux = 0.0
        uy = 0.0
        for k in range(4):
            ux += N[p, k] * ux_n[nodes[p, k]]
            uy += N[p, k] * uy_n[nodes[p, k]]
        out[p] = cubic_point(c, bx[p] + ux * isx, by[p] + uy * isy, hi0, hi1)
        if has_sub:
            out[p] -= sub[p]
    return out


@_jit
def gradient_nodes(w, res, gx, gy, nodes, N, out):  # pragma: no cover - compiled
    """out[2 n + a] += sum_p N_n(p) w_p r_p g_a(p) (interleaved nodal vector)."""
    for p in range(w.shape[0]):
        v = w[p] * res[p]
        vx = v * gx[p]
        vy = v * gy[p]
        for k in range(4):
            out[2 * nodes[p, k]] += N[p, k] * vx
            out[2 * nodes[p, k] + 1] += N[p, k] * vy


@_jit
def element_blocks(w, gx, gy, N, nodes, elem, t, n_el):  # pragma: no cover - compiled
    """Per-element sums ``S[e, k, l, c] = sum_p w_p N_k N_l G_c`` (k <= l in the element's own node order
    ``t[:, e]``; G = (gx^2, gx gy, gy^2)) from which the 8 x 8 blocks of sum_p w_p (N_p (x) g_p)(N_p (x) g_p)^T
    follow by symmetry (a pixel's ``nodes`` may list the element's corners in another order)."""
    S = np.zeros((n_el, 4, 4, 3))
    loc = np.empty(4, dtype=np.int64)
    for p in range(w.shape[0]):
        e = elem[p]
        for k in range(4):
            for l in range(4):
                if t[l, e] == nodes[p, k]:
                    loc[k] = l
        g0 = gx[p]
        g1 = gy[p]
        for k in range(4):
            wk = w[p] * N[p, k]
            for l in range(k, 4):
                s = wk * N[p, l]
                a = min(loc[k], loc[l])
                b = max(loc[k], loc[l])
                S[e, a, b, 0] += s * g0 * g0
                S[e, a, b, 1] += s * g0 * g1
                S[e, a, b, 2] += s * g1 * g1
    return S


@_jit
def walk_kernel(x, y, px, py, cn, cell, rows, cols, steps, tol, restol, elem, X, Y, nodes):  # pragma: no cover
    """Compiled twin of :meth:`PointLocator._walk` (same guess, Newton inversion, acceptance and steps)."""
    nxe, nye = cell.shape
    for p in range(x.shape[0]):
        a = min(max(np.searchsorted(rows, x[p]) - 1, 0), nxe - 1)
        b = min(max(np.searchsorted(cols, y[p]) - 1, 0), nye - 1)
        for _ in range(steps):
            n0, n1, n2, n3 = cn[a, b, 0], cn[a, b, 1], cn[a, b, 2], cn[a, b, 3]
            ax0, ax1, ax2, ax3 = px[n0], px[n1] - px[n0], px[n3] - px[n0], px[n0] - px[n1] + px[n2] - px[n3]
            ay0, ay1, ay2, ay3 = py[n0], py[n1] - py[n0], py[n3] - py[n0], py[n0] - py[n1] + py[n2] - py[n3]
            # start from the cell's place between the mean row / column positions (exact for a rectangle)
            Xc = min(max((x[p] - rows[a]) / (rows[a + 1] - rows[a]), 0.0), 1.0)
            Yc = min(max((y[p] - cols[b]) / (cols[b + 1] - cols[b]), 0.0), 1.0)
            for _it in range(12):
                rx = x[p] - (ax0 + ax1 * Xc + ax2 * Yc + ax3 * Xc * Yc)
                ry = y[p] - (ay0 + ay1 * Xc + ay2 * Yc + ay3 * Xc * Yc)
                j00, j01 = ax1 + ax3 * Yc, ax2 + ax3 * Xc
                j10, j11 = ay1 + ay3 * Yc, ay2 + ay3 * Xc
                det = j00 * j11 - j01 * j10
                if det == 0.0:
                    det = 1e-300
                dX = (j11 * rx - j01 * ry) / det
                dY = (-j10 * rx + j00 * ry) / det
                Xc += dX
                Yc += dY
                if abs(dX) < 1e-13 and abs(dY) < 1e-13:
                    break
            rx = x[p] - (ax0 + ax1 * Xc + ax2 * Yc + ax3 * Xc * Yc)
            ry = y[p] - (ay0 + ay1 * Xc + ay2 * Yc + ay3 * Xc * Yc)
            if not np.isfinite(Xc + Yc):
                break
            if (Xc >= -tol and Xc <= 1 + tol and Yc >= -tol and Yc <= 1 + tol
                    and np.sqrt(rx * rx + ry * ry) <= restol):
                elem[p] = cell[a, b]
                X[p] = min(max(Xc, 0.0), 1.0)
                Y[p] = min(max(Yc, 0.0), 1.0)
                nodes[p, 0], nodes[p, 1], nodes[p, 2], nodes[p, 3] = n0, n1, n2, n3
                break
            na = a + (1 if Xc > 1 + tol else (-1 if Xc < -tol else 0))
            nb = b + (1 if Yc > 1 + tol else (-1 if Yc < -tol else 0))
            na = min(max(na, 0), nxe - 1)
            nb = min(max(nb, 0), nye - 1)
            if na == a and nb == b:
                break
            a, b = na, nb


# -- analytic signal of the pyramid's speckle statistics and envelopes (femreg.pyramid) -----------------------


@_jit
def hilbert_half_spectrum(X, n_pos, power):  # pragma: no cover - compiled
    """Half spectrum of the Hilbert transform of the columns of ``X`` (axial rfft, rows = frequencies): ``-i X``
    on rows 1 .. n_pos - 1, 0 elsewhere, and, when ``power`` has X's shape, ``|X|^2`` into it; one pass instead
    of numpy's product with a sign array and separate squares of the real and imaginary parts."""
    nr, nc = X.shape
    out = np.zeros((nr, nc), np.complex128)
    want_power = power.shape[0] == nr
    for i in range(nr):
        inside = i >= 1 and i < n_pos
        for j in range(nc):
            v = X[i, j]
            if inside:
                out[i, j] = complex(v.imag, -v.real)
            if want_power:
                power[i, j] = v.real * v.real + v.imag * v.imag
    return out


@_jit
def modulus(a, b):  # pragma: no cover - compiled
    """sqrt(a^2 + b^2) elementwise over a's shape (b may have more rows): one pass, no temporaries."""
    nr, nc = a.shape
    out = np.empty((nr, nc))
    for i in range(nr):
        for j in range(nc):
            out[i, j] = np.sqrt(a[i, j] * a[i, j] + b[i, j] * b[i, j])
    return out


@_jit
def to_complex(a, b):  # pragma: no cover - compiled
    """a + i b over a's shape (b may have more rows), in one pass."""
    nr, nc = a.shape
    out = np.empty((nr, nc), np.complex128)
    for i in range(nr):
        for j in range(nc):
            out[i, j] = complex(a[i, j], b[i, j])
    return out


@_jit
def lag_products(a, k0, k1):  # pragma: no cover - compiled
    """``out[k - k0] = sum a[i, j] a[i + k, j]`` over the pixel pairs of ``a`` k rows apart, k0 <= k < k1:
    several lags per pass over the image (the rows stay in cache); per-column accumulators keep the inner loop
    vectorisable."""
    n0, n1 = a.shape
    nk = k1 - k0
    acc = np.zeros((nk, n1))
    for i in range(n0):
        for q in range(nk):
            i2 = i + k0 + q
            if i2 >= n0:
                break
            for j in range(n1):
                acc[q, j] += a[i, j] * a[i2, j]
    out = np.zeros(nk)
    for q in range(nk):
        for j in range(n1):
            out[q] += acc[q, j]
    return out


@_jit
def tricubic_grid(c, hi0, hi1, hi2, bxr, byc, bzl, bx, by, bz, ux, uy, uz, isx, isy, isz, sub,
                  out):  # pragma: no cover - compiled
    """Tricubic B-spline interpolant (coefficients ``c`` mirror-padded by 2) at base + u / spacing over an
    (nr, nc, nl) voxel block, minus ``sub`` (I_1 for the residual; empty for I_2 alone); 0 outside the voxel
    cells [-1/2, n - 1/2].  The base index is bxr[r], byc[q], bzl[s] per axis, or with ``bx`` non-empty the full
    (nr, nc, nl) arrays bx, by, bz (an offset S).  ``ux``, ``uy``, ``uz`` (nr, nc, nl) mm: u at the voxels.
    The values of ``map_coordinates(order=3, prefilter=False)`` on the padded coefficients."""
    nr, nc, nl = ux.shape
    full = bx.shape[0] > 0
    has_sub = sub.shape[0] > 0
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    for r in range(nr):
        for q in range(nc):
            for s in range(nl):
                if full:
                    xp = bx[r, q, s] + ux[r, q, s] * isx
                    yp = by[r, q, s] + uy[r, q, s] * isy
                    zp = bz[r, q, s] + uz[r, q, s] * isz
                else:
                    xp = bxr[r] + ux[r, q, s] * isx
                    yp = byc[q] + uy[r, q, s] * isy
                    zp = bzl[s] + uz[r, q, s] * isz
                k = (r * nc + q) * nl + s
                v = 0.0
                if xp >= -0.5 and xp <= hi0 and yp >= -0.5 and yp <= hi1 and zp >= -0.5 and zp <= hi2:
                    fx = np.floor(xp)
                    fy = np.floor(yp)
                    fz = np.floor(zp)
                    wx[0], wx[1], wx[2], wx[3] = _cubic_weights(xp - fx)
                    wy[0], wy[1], wy[2], wy[3] = _cubic_weights(yp - fy)
                    wz[0], wz[1], wz[2], wz[3] = _cubic_weights(zp - fz)
                    i0 = int(fx) + 1
                    j0 = int(fy) + 1
                    l0 = int(fz) + 1
                    for a in range(4):
                        va = 0.0
                        for b in range(4):
                            row = c[i0 + a, j0 + b]
                            va += wy[b] * (wz[0] * row[l0] + wz[1] * row[l0 + 1] + wz[2] * row[l0 + 2]
                                           + wz[3] * row[l0 + 3])
                        v += wx[a] * va
                out[k] = v - sub[k] if has_sub else v
    return out
