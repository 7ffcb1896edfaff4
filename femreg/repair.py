"""Check and repair stage of :func:`femreg.register`: per-element quality, peak-hopping detection and repair,
and the rule that a result never explains less of the image than its start.

Peak hopping: from a start more than about a quarter of the RF period off, Gauss-Newton on RF converges to the
neighbouring correlation peak, one period T off in u_x (bands of +-T in u_x, stripes in e_xx).  It is detected
node by node: u_x minus a robust reference (the coarser level's field plus the local median of the difference,
or the local median of u_x less its affine part when there is no coarser level) is more than :data:`HOP_FRACTION`
of T away from zero.  Such nodes are reseeded by whole periods towards the reference and the solve is repeated.
When the speckle decorrelates (rotation, large strain) the coarser level can hold the same wrong island; after the
coarse-level repair, :func:`femreg.register` therefore also reseeds nodes whole periods off their own neighbourhood
and keeps the result only if the energy falls (near an inclusion at several percent strain a smooth field can look
like such an offset, and there the reseeded solve explains the pair worse).

Quality map: the NCC of reference and warped moving image over the pixels of each element (1 = perfect match;
speckle decorrelation lowers it smoothly, a hop or a failure drops it towards 0).

Hop check (:func:`hop_gain`), from the result alone, for every strategy: a hopped element still matches the RF
well (the neighbouring correlation peak of a pulse of 2-3 cycles is high: element NCC 0.73-0.77 on the elements one
period off of the paper procedure's wrong results in the robustness benchmark, against 0.92-0.995 where right, so
the quality map misses it), but its envelope is then one period off.  Per element, the envelope NCC of the reference and the warped
moving image is compared at u and at u shifted axially by +-1 RF period; where a shifted u explains the envelope
better, the element sits on a neighbouring peak.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from . import _kernels
from .errors import counted
from .image import ncc
from .mesh import tensor_node_grid, tensor_structure
from .pixels import pixel_values  # noqa: F401  (also femreg.repair.pixel_values)
from .pyramid import ROTATION_SCAN_NCC
from .speckle import rf_period

__all__ = ["element_ncc", "pixel_values", "hop_nodes", "reseed", "poor_fraction", "hop_gain", "hopped_fraction",
           "repair_peak_hopping", "envelope_lag_ncc", "envelope_lag_ncc_3d",
           "lag_gain", "hop_note", "check_result", "frame_flag", "check_period", "Check", "MAX_POOR_FRACTION_DECORRELATED",
           "retry_flagged", "keep_retry",
           "HOP_FRACTION", "PSI_SLACK", "MIN_NCC", "MAX_POOR_FRACTION", "HOP_GAIN", "MAX_HOPPED_FRACTION",
           "mark_tainted", "own_flag", "summarise_flags", "TAINT_PREFIX"]

#: A node is hopping when ``|u_x - reference|`` exceeds this fraction of the RF period.
HOP_FRACTION = 0.35
#: A registration whose NCC after is below this is reported as failed: unrelated speckle images reach
#: 0.14-0.17 with the default mesh (measured, tests/test_robust.py), real pairs 0.5-0.99 (in vivo 1 -> 6:
#: 0.80 / 0.88).
MIN_NCC = 0.3
#: A registration with more than this fraction of its elements below :data:`MIN_NCC` (quality map) is reported as
#: failed: wrong correlation peaks over whole regions (measured on the robustness benchmark with the paper's
#: procedure: 37-79 % of the elements on the pairs it gets wrong; 0-17 % on every default registration there and
#: on the in vivo pairs frames 1 -> 2 ... 1 -> 6, the paper's procedure up to 24 %).
MAX_POOR_FRACTION = 0.3
#: The same limit on a strongly decorrelated pair (global envelope NCC below
#: :data:`femreg.pyramid.ROTATION_SCAN_NCC`): there a tenth of the elements not matching marks a wrong result
#: (5 % compression + 5 degrees under a 12 MHz probe: 27 % of the elements, 19 % total strain error), while no
#: correct registration of the robustness benchmark, the rotation sweep or the in vivo pairs is both decorrelated
#: and above a tenth.
MAX_POOR_FRACTION_DECORRELATED = 0.1
#: An element counts as hopped when the envelope matches better one RF period off than at u by more than this
#: Fisher-z gain (:func:`hop_gain`).  Measured: the hopped elements of the paper procedure's wrong results on the
#: robustness benchmark reach 1.3-1.7; the largest gain on a correct registration is below 0 on every simulated
#: pair and 0.4-0.5 on most in vivo elements flagged at all (decorrelated speckle, frames 1 -> 6).
HOP_GAIN = 0.5
#: A registration with more than this fraction of hopped elements is reported as failed.  Measured (elements with
#: gain > :data:`HOP_GAIN`): correct results 0 % on all 17 simulated benchmark pairs (every regulariser, both
#: strategies where right), at most 0.9 % on the in vivo pairs frames 1 -> 6 (register and track); wrong results
#: of the paper procedure 4.6 % (shear, 1 % compression, L7) to 51 % (stiff inclusion, 4 %).  2 % sits a factor
#: 2.2 above the largest correct value and 2.3 below the smallest wrong one.
MAX_HOPPED_FRACTION = 0.02


def _pixel_elements(quad) -> np.ndarray:
    """Element of each quadrature pixel (n_pixels,); on tensor meshes from the separable grid description."""
    gr = quad.location.grid
    if gr is None:
        return quad.location.element
    cell = quad.locator.tensor[2]
    return cell[gr.i[:, None], gr.j[None, :]].ravel()


def element_ncc(data, u, n_elements: int, groups=None) -> np.ndarray:
    """NCC of reference and warped moving image over each element's pixels, (n_elements,); NaN for elements
    with fewer than 4 pixels.  ``data`` is the :class:`femreg.data_term.SSDTerm` of the solve.  ``groups``
    (n_elements,) int: the NCC over the pixels of each group of elements instead (a refined mesh's unrefined
    parent cells, :func:`femreg.refine.parent_cells`), (groups.max() + 1,).  Pixels a fan's fill leaves out of
    eq:IR (``data.fan_keep`` False, :func:`femreg.gnsolve.image_term`) are left out here too."""
    a = data.ref_values
    b = data.residual(u) + a
    gr = data.quad.location.grid
    keep = getattr(data, "fan_keep", None)
    if keep is not None and not np.all(keep):
        # a fan's fill is the same in both frames (constant, or zero RF): its pixels would read as a mismatch
        el = _pixel_elements(data.quad) if groups is None else np.asarray(groups, np.int64)[_pixel_elements(data.quad)]
        n = n_elements if groups is None else int(np.max(groups)) + 1
        q, cnt = _group_ncc(el[keep], a[keep], b[keep], n)
        q[cnt < 4] = np.nan
        return q
    if groups is not None:
        groups = np.asarray(groups, np.int64)
        q, cnt = _group_ncc(groups[_pixel_elements(data.quad)], a, b, int(groups.max()) + 1)
        q[cnt < 4] = np.nan
        return q
    if gr is not None and _kernels.use_compiled() and np.all(np.diff(gr.i) >= 0) and np.all(np.diff(gr.j) >= 0):
        # tensor mesh: pixel rows x columns of each element are consecutive; one compiled pass per moment
        rseg = np.cumsum(np.diff(gr.i, prepend=gr.i[0]) > 0)
        cseg = np.cumsum(np.diff(gr.j, prepend=gr.j[0]) > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            qb, cb = _kernels.block_ncc(np.ascontiguousarray(a), np.ascontiguousarray(b), rseg, cseg,
                                        int(rseg[-1]) + 1, int(cseg[-1]) + 1)
        cell = data.quad.locator.tensor[2][np.unique(gr.i)[:, None], np.unique(gr.j)[None, :]]
        q = np.full(n_elements, np.nan)
        cnt = np.zeros(n_elements)
        q[cell.ravel()], cnt[cell.ravel()] = qb.ravel(), cb.ravel()
        q[cnt < 4] = np.nan
        return q
    q, cnt = _group_ncc(_pixel_elements(data.quad), a, b, n_elements)
    q[cnt < 4] = np.nan
    return q


def _group_ncc(groups, x, y, n: int):
    """NCC of ``x`` and ``y`` ((m,), or (k, m) for k at once) within each group (``groups`` (m,) in 0 .. n - 1):
    group means first, then the centred sums (two passes, as :func:`femreg._kernels.block_ncc`).  Returns
    (ncc (n,) or (k, n), count (n,)); NaN where a group has no variance."""
    Y = np.asarray(y, float).reshape(-1, len(groups))
    if _kernels.use_compiled():
        q, cnt = _kernels.group_ncc(np.asarray(groups, np.int64), np.asarray(x, float), Y, int(n))
    else:
        cnt = np.bincount(groups, minlength=n).astype(float)[:n]
        q = np.empty((Y.shape[0], n))
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = x - (np.bincount(groups, x, n) / cnt)[groups]
            sxx = np.bincount(groups, dx * dx, n)
            for i, yi in enumerate(Y):
                dy = yi - (np.bincount(groups, yi, n) / cnt)[groups]
                q[i] = np.bincount(groups, dx * dy, n) / np.sqrt(sxx * np.bincount(groups, dy * dy, n))
    return (q[0] if np.ndim(y) == 1 else q), cnt


def poor_fraction(quality) -> float:
    """Fraction of the elements (with a finite quality) whose element NCC is below :data:`MIN_NCC`."""
    q = np.asarray(quality, float)
    q = q[np.isfinite(q)]
    return float(np.mean(q < MIN_NCC)) if q.size else 1.0


def _node_median(mesh, values, size: int = 5) -> np.ndarray:
    """Median of a nodal scalar over a size x size node neighbourhood (tensor meshes and meshes with their
    connectivity) or over the 2-ring of neighbours (other meshes)."""
    ts = tensor_structure(mesh)
    if ts is not None:
        G = tensor_node_grid(mesh, ts[0], ts[1])
    else:
        from .pixels import logical_grid

        lg = logical_grid(mesh)          # a moved tensor mesh (femreg.track): the same filter on its node grid
        G = None if lg is None else lg[0]
    if G is not None:
        out = np.empty(G.size)
        out[G.ravel()] = ndimage.median_filter(np.asarray(values, float)[G], size=size, mode="nearest").ravel()
        return out
    import scipy.sparse as sp

    t = np.asarray(mesh.t)
    n = mesh.p.shape[1]
    r = np.repeat(t, t.shape[0], axis=0).ravel()
    c = np.tile(t, (t.shape[0], 1)).ravel()
    A = sp.csr_matrix((np.ones(r.size), (r, c)), shape=(n, n))
    A2 = (A @ A).tocsr()
    out = np.empty(n)
    for i in range(n):
        out[i] = np.median(values[A2.indices[A2.indptr[i]:A2.indptr[i + 1]]])
    return out


def hop_nodes(mesh, ux, period: float, reference=None) -> np.ndarray:
    """Integer number of RF periods by which each node's u_x is off its robust reference (0 = fine).

    ``reference`` (n_nodes,) is the coarser level's u_x at the nodes (None: the local median of ``ux`` less its
    least-squares affine part, so that the median's bias at the mesh edges, where the window is one-sided, does
    not read a steep but smooth field -- a rotation -- as offsets)."""
    ux = np.asarray(ux, float)
    if reference is None:
        A = np.column_stack([np.ones(ux.size), mesh.p[0], mesh.p[1]])
        r = ux - A @ np.linalg.lstsq(A, ux, rcond=None)[0]
        d = r - _node_median(mesh, r)
    else:
        d0 = ux - np.asarray(reference, float)
        d = d0 - _node_median(mesh, d0)
    k = np.round(d / period)
    k[np.abs(d - k * period) > HOP_FRACTION * period] = 0       # not a whole-period offset
    k[np.abs(d) <= HOP_FRACTION * period] = 0
    return k.astype(int)


def reseed(u, k, period: float) -> np.ndarray:
    """``u`` with u_x of every node moved by -k periods (the start of the repeated solve)."""
    out = np.array(u, float, copy=True)
    out[0::2] -= k * period
    return out


def hop_gain(data, u, n_elements: int, period: float, shape, spacing, groups=None) -> np.ndarray:
    """Per element, how much better u shifted axially by one RF period explains the envelope, (n_elements,):
    ``atanh(max(c(-T), c(+T))) - atanh(c(0))`` (Fisher z of the NCCs of :func:`envelope_lag_ncc`, so that a gain
    between well-matched envelopes weighs more than the same difference between noisy ones).  Negative on a
    correct result (the envelope correlation peaks at lag 0), positive where the element sits a period off.
    ``groups``: per group of elements instead (:func:`envelope_lag_ncc`)."""
    return lag_gain(envelope_lag_ncc(data, u, n_elements, period, shape, spacing, groups=groups))


def lag_gain(c) -> np.ndarray:
    """The hop gain ``atanh(max(c(-T), c(+T))) - atanh(c(0))`` of envelope lag NCCs ``c`` (3, n_elements) (the
    lags -T, 0, +T; :func:`envelope_lag_ncc`, :func:`envelope_lag_ncc_3d`)."""
    c = np.clip(c, -0.999, 0.999)
    return np.arctanh(np.fmax(c[0], c[2])) - np.arctanh(c[1])


def _half_period_edges(row0: int, nr: int, L: float) -> np.ndarray:
    """Row edges (relative to ``row0``, inside [0, nr)) of half-period blocks laid on the image's (volume's) rows
    from row 0 (``L`` rows per RF period), so that the blocks are the same whatever part of the image is used."""
    edges = np.unique(np.round(np.arange(0.0, row0 + nr + 1e-9, 0.5 * L)).astype(np.int64)) - row0
    return edges[(edges >= 0) & (edges < nr)]


def _window_envelopes(Qa, Qw, k):
    """Envelopes of the one-period windows ``k`` (window k = half-period blocks k, k + 1) from block energies
    ``Qa``, ``Qw`` (n_blocks, ...): the reference's at k and the warped moving image's at k - 2, k, k + 2 (one
    period up, here, one period down).  Returns ``(x (len(k), ...), y (3, len(k), ...))``."""
    x = np.sqrt(np.add(Qa[k], Qa[k + 1], dtype=float))
    y = np.stack([np.sqrt(np.add(Qw[k + s], Qw[k + s + 1], dtype=float)) for s in (-2, 0, 2)])
    return x, y


def _lag_windows(data, u, period: float, shape, spacing):
    """The one-period windows of :func:`envelope_lag_ncc`: ``(el, ok, x, y)``, each window's element (-1 outside the
    mesh), whether it counts, the reference envelope (n_windows, n_cols) and the warped moving one at -T, 0, +T
    (3, ...); None where the image holds too few periods.  Kept on ``data`` for the last ``u`` (read-only): the
    check of a refined result reads them per element and per unrefined parent cell (0.09 of its 0.18 s on a
    60 x 40 mm refined pair were the second reading)."""
    u = np.asarray(u, float)
    # the compiled switch is part of the key: the numpy twin is computed when it is off (its tests compare both)
    key = (float(period), tuple(int(v) for v in shape), tuple(float(v) for v in np.ravel(spacing)),
           _kernels.use_compiled())
    hit = getattr(data, _LAG_ATTR, None)
    if hit is not None and hit[1] == key and hit[0].shape == u.shape and np.array_equal(hit[0], u):
        return hit[2]
    out = _lag_windows_of(data, u, period, shape, spacing)
    if out is not None:
        for v in out:
            v.flags.writeable = False
    try:
        setattr(data, _LAG_ATTR, (u.copy(), key, out))
    except (AttributeError, TypeError):   # pragma: no cover - an image term that takes no attributes: not kept
        pass
    return out


#: Attribute of an image term holding :func:`_lag_windows` of the last displacement.
_LAG_ATTR = "_femreg_lag_windows"


def _lag_windows_of(data, u, period: float, shape, spacing):
    """:func:`_lag_windows` computed."""
    n0, n1 = (int(s) for s in shape)
    L = float(period) / float(spacing[0])                  # rows per period
    if not (np.isfinite(L) and L >= 2.0):
        return None
    quad = data.quad
    a = data.ref_values
    res = data.residual(u)
    gr = quad.location.grid
    row0 = 0
    if gr is not None:                  # tensor mesh: the quadrature pixels are an nr x nc block of the image
        nr = gr.nr
        row0 = int(quad.index[0]) // n1 if quad.index.size else 0
        cell = quad.locator.tensor[2][:, gr.j]
        row_el, M2 = gr.i, None
    else:                               # any mesh: scatter onto the image grid, windows must lie inside the mesh
        nr = n0
        w = np.add(res, a)
        np.multiply(w, w, out=w)
        A2, W2, M2 = np.zeros(n0 * n1), np.zeros(n0 * n1), np.zeros(n0 * n1)
        A2[quad.index], W2[quad.index], M2[quad.index] = a * a, w, 1.0
        A2, W2, M2 = A2.reshape(n0, n1), W2.reshape(n0, n1), M2.reshape(n0, n1)
        E = np.full(n0 * n1, -1, dtype=np.int64)
        E[quad.index] = _pixel_elements(quad)
        cell, row_el = E.reshape(n0, n1), np.arange(n0)
    # half-period blocks on the image's rows (the same blocks whichever branch above)
    edges = _half_period_edges(row0, nr, L)
    nb = edges.size - 1                 # whole half-period blocks [edges[k], edges[k + 1])
    if nb < 7:
        return None
    if M2 is None and _kernels.use_compiled():
        Qa, Qw = _kernels.block_energies(a, res, a.size // nr, edges.astype(np.int64), nb)
    else:
        if M2 is None:
            w = np.add(res, a)
            A2, W2 = (a * a).reshape(nr, -1), np.multiply(w, w, out=w).reshape(nr, -1)
        Qa = np.add.reduceat(A2, edges, axis=0)[:nb]
        Qw = np.add.reduceat(W2, edges, axis=0)[:nb]
    k = np.arange(2, nb - 3)            # windows with both partners one period (two blocks) away
    el = cell[row_el[edges[k + 1]]]
    ok = el >= 0
    if M2 is not None:
        full = np.add.reduceat(M2, edges, axis=0)[:nb]
        full = (full[:-1] + full[1:]) >= (edges[2:] - edges[:-2])[:, None] - 0.5
        ok &= full[k] & full[k - 2] & full[k + 2]
    x, y = _window_envelopes(Qa, Qw, k)
    return el, ok, x, y


def envelope_lag_ncc(data, u, n_elements: int, period: float, shape, spacing, groups=None) -> np.ndarray:
    """NCC over each element of the reference envelope at x and the warped moving envelope at x - T, x, x + T
    (T = ``period`` mm, axial), (3, n_elements); NaN where an element has fewer than 8 envelope samples.

    ``data`` is the :class:`femreg.data_term.SSDTerm` of the solve (its reference values and the warped moving
    image I_2(x + S + u) at the quadrature pixels): no new warp, the warped image one period further in depth is
    I_2 at x + S + u + T up to the strain times T.  The envelope is the square root of the RF energy in
    one-period windows sampled every half period (block sums of squares over half-period blocks; no Hilbert
    transform: one pass over the pixels).  ``shape``, ``spacing``: the reference pixel grid that ``data.quad``
    indexes.  ``groups`` (n_elements,) int: the NCC over each group of elements instead (a refined mesh's
    unrefined parent cells, :func:`femreg.refine.parent_cells`), (3, groups.max() + 1)."""
    if groups is not None:
        groups = np.asarray(groups, np.int64)
        n_elements = int(groups.max()) + 1
    win = _lag_windows(data, u, period, shape, spacing)
    if win is None:
        return np.full((3, n_elements), np.nan)
    el, ok, x, y = win
    if groups is not None:
        el = np.where(ok, groups[np.maximum(el, 0)], -1)
    c, cnt = _group_ncc(el[ok], x[ok], y[:, ok], n_elements)
    c[:, cnt < 8] = np.nan
    return c


#: Voxels per slab of :func:`envelope_lag_ncc_3d` (its temporaries take about 200 bytes each).
LAG_CHUNK_3D = 1 << 17


def envelope_lag_ncc_3d(data, warped, period: float) -> np.ndarray:
    """The volume form of :func:`envelope_lag_ncc`: NCC over each hexahedron of the reference envelope at x and
    the warped moving envelope at x - T, x, x + T (T = ``period`` mm, axial), (3, n_elements) in ``mesh.t``
    order; NaN where an element has fewer than 8 envelope samples or ``period`` is under 2 voxels.

    ``data``: the :class:`femreg.voxels.VoxelSSDTerm` of the solve (its voxel grid and reference values);
    ``warped``: I_2(x + S + u) at its voxels (nr, nc, nl).  The same half-period blocks and one-period windows
    as in 2D (:func:`_half_period_edges`, :func:`_window_envelopes`); the element NCCs from element sums of the
    window moments (separable, as :meth:`femreg.voxels.VoxelGrid.element_sums`) accumulated slab by slab, so no
    temporary is the size of the volume: the block energies take 8 bytes per half period and (y, z) line."""
    grid = data.grid
    nr, nc, nl = data.shape
    n_el = grid.mesh.t.shape[1]
    nan = np.full((3, n_el), np.nan)
    L = float(period) / float(grid.spacing[0])
    if not (np.isfinite(L) and L >= 2.0):
        return nan
    edges = _half_period_edges(grid.block[0].start, nr, L)
    nb = edges.size - 1
    if nb < 7:
        return nan
    a, w = data.ref_values, warped
    Qa = np.empty((nb, nc, nl), np.float32)
    Qw = np.empty((nb, nc, nl), np.float32)
    per = max(1, int(LAG_CHUNK_3D // max(1, nc * nl) / (0.5 * L)))         # blocks per slab
    for b0 in range(0, nb, per):
        b1 = min(nb, b0 + per)
        r0, r1 = int(edges[b0]), int(edges[b1])
        loc = edges[b0:b1] - r0
        Qa[b0:b1] = np.add.reduceat(np.square(a[r0:r1], dtype=float), loc, axis=0)
        Qw[b0:b1] = np.add.reduceat(np.square(w[r0:r1], dtype=float), loc, axis=0)
    # element sums of the window moments: along y and z by blocks of columns, along x by each window's element row
    E = tuple(s - 1 for s in grid.node_shape)
    yz = []
    for ax in (1, 2):
        e = grid.e[ax]
        st = np.flatnonzero(np.diff(e, prepend=-2))
        yz.append((st, e[st]))

    def sum_yz(V):
        out = np.add.reduceat(np.add.reduceat(V, yz[0][0], axis=1), yz[1][0], axis=2)
        full = np.zeros((V.shape[0],) + E[1:])
        full[:, yz[0][1][:, None], yz[1][1][None, :]] = out
        return full

    k_all = np.arange(2, nb - 3)        # windows with both partners one period (two blocks) away
    ex_all = grid.e[0][edges[k_all + 1]]
    M = np.zeros((12,) + E)             # n, Sx, Sxx, Sy (3), Syy (3), Sxy (3)
    per = max(1, int(LAG_CHUNK_3D // max(1, nc * nl)))
    for k0 in range(0, k_all.size, per):
        k, ex = k_all[k0:k0 + per], ex_all[k0:k0 + per]
        x, y = _window_envelopes(Qa, Qw, k)
        st = np.flatnonzero(np.diff(ex, prepend=-2))        # windows are in depth order: runs of one element row
        parts = (np.ones_like(x), x, x * x, *y, *(y * y), *(x[None] * y))
        for i, V in enumerate(parts):
            M[i][ex[st]] += sum_yz(np.add.reduceat(V, st, axis=0))
    n = M[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = M[1] / n
        vx = M[2] / n - mx * mx
        my = M[3:6] / n
        c = (M[9:12] / n - mx * my) / np.sqrt(vx * (M[6:9] / n - my * my))
    c[:, n < 8] = np.nan
    out = np.full((3, n_el), np.nan)
    out[:, grid.cell.ravel()] = c.reshape(3, -1)
    return out


def hop_note(hopped: float, period: float) -> str:
    """The failure note of a result with ``hopped`` (fraction) of its elements one RF period off."""
    return f"peak hopping: {hopped:.0%} of the elements match the envelope better one RF period ({period:.3g} mm) off"


def hopped_fraction(gain) -> float:
    """Fraction of the elements (with a finite :func:`hop_gain`) that sit one RF period off (gain above
    :data:`HOP_GAIN`)."""
    g = np.asarray(gain, float)
    g = g[np.isfinite(g)]
    return float(np.mean(g > HOP_GAIN)) if g.size else 0.0


def repair_peak_hopping(sol, resolve, mesh, period: float, reference=None):
    """Repair stage of :func:`femreg.register` (module docstring): reseed nodes whole RF periods off and solve again.

    ``sol``: the solve (:class:`femreg.gnsolve.Solve`); ``resolve(u_start)`` solves again from a reseeded start;
    ``reference``: the coarse level's nodal u_x (n_nodes,), or None.  First (at most twice) nodes off the coarse
    level, whose repair is kept when the energy does not rise or the coarse level is trusted; then (with a coarse
    level, at most twice) islands off their own neighbourhood, kept only if the energy falls.  Returns ``(sol,
    hops, notes)``: the kept solve, the nodes still whole periods off the coarse level (int, in periods) and the
    notes for the message."""
    notes = []

    def total(s):
        return s.data.energy(s.u) + s.reg.energy(s.u)

    hops = np.zeros(mesh.p.shape[1], int)
    checked = sol
    for _ in range(2):          # whole-period offsets from the coarse level: the coarse level is trusted
        hops = hop_nodes(mesh, sol.u[0::2], period, reference)
        checked = sol
        if not hops.any():
            break
        notes.append(f"peak hopping at {counted(int(np.count_nonzero(hops)), 'node')} reseeded")
        again = resolve(reseed(sol.u, hops, period))
        if total(again) <= total(sol) or reference is not None:
            sol = again
    for _ in range(2 if reference is not None else 0):
        # islands whole periods off their own neighbourhood, which the coarse level shares (decorrelated
        # pairs): kept only if the energy falls -- near an inclusion at several percent strain a smooth field
        # can look like such offsets, and there the reseeded solve explains the pair much worse
        islands = hop_nodes(mesh, sol.u[0::2], period, None)
        if not islands.any():
            break
        again = resolve(reseed(sol.u, islands, period))
        if not total(again) <= total(sol):
            break
        notes.append(f"peak hopping at {counted(int(np.count_nonzero(islands)), 'node')} off their neighbours reseeded")
        sol = again
    if sol is not checked:      # a repair moved the result: test it again against the coarse level
        hops = hop_nodes(mesh, sol.u[0::2], period, reference)
    return sol, hops, notes


@dataclass
class Check:
    """Outcome of :func:`check_result`: ``success``, the returned nodal ``u`` (2 n_nodes,), the ``notes`` for the
    message, NCC over the mesh pixels at u = 0 and at ``u``, the per-element NCC (``quality``) and the
    peak-hopping map (``hop_gain``, None for single-row images)."""

    success: bool
    u: np.ndarray
    notes: list
    ncc_before: float
    ncc_after: float
    quality: np.ndarray
    hop_gain: np.ndarray | None


def check_period(ref, spacing, stats=None) -> float:
    """RF period (mm) for the hop check: the speckle statistics' if known, else from every k-th line (>= 32 lines:
    as precise, a quarter of the cost on a paper-size image)."""
    return stats.period if stats is not None else rf_period(ref[:, ::max(1, ref.shape[1] // 32)], spacing)


#: Envelope / B-mode data: how much less of the image the regularised result may explain than its start before the
#: never-worse rule refuses it.  The start is then a fit of the same image without the regulariser (for RF it is
#: an envelope fit, which the RF solve always improves on); measured +0.26 % on the paper probe's 1 % pair.
ENVELOPE_PSI_SLACK = 0.02
#: RF data: how much less of the image (relative psi of eq:objf) the regularised result may explain than its start
#: when eq:objf itself fell (the regulariser bought the difference).  A track increment started from an already
#: exact previous increment trades a little psi for a smoother field: measured +0.004 to +0.15 % psi (eq:objf
#: -0.5 %) on 11 of 36 uniform loops (0.2-0.5 %/frame, 3 steps), which the former round-off slack of 1e-9 failed;
#: a result that does explain less (strain regulariser, alpha 10-1e5 from a registered start, 1 % compression):
#: +0.9 % to +11000 %.  0.5 % sits 3.3 x above the former and 1.8 x below the smallest of the latter.
PSI_SLACK = 0.005
#: The note of a result registered on envelope / B-mode frames.
ENVELOPE_NOTE = ("envelope / B-mode data (no RF carrier along the depth): no peak-hopping check or repair, which need "
                 "the carrier; displacements are those of the envelope (less precise than RF)")


def _explains_less(sol, u0, u, psi_start, psi_final, envelope) -> bool:
    """The never-worse rule: the result ``u``'s psi ``psi_final`` (eq:objf's image term) exceeds its start ``u0``'s
    ``psi_start`` by more than round-off, and either by more than :data:`ENVELOPE_PSI_SLACK` (envelope) /
    :data:`PSI_SLACK` (RF) relative, or without eq:objf (psi plus ``sol.reg``) having fallen."""
    if not psi_final > psi_start * (1.0 + 1e-9) + 1e-300:
        return False
    if psi_final > psi_start * (1.0 + (ENVELOPE_PSI_SLACK if envelope else PSI_SLACK)):
        return True
    # within the slack: kept only when the regulariser bought the difference
    return not psi_final + sol.reg.energy(u) < psi_start + sol.reg.energy(u0)


def check_result(sol, u0, hops, shape, spacing, period=None, global_ncc=None, groups=None,
                 envelope: bool = False) -> Check:
    """Check stage of :func:`femreg.register`: the failure rules, the never-worse rule and the quality maps.

    ``sol``: the final solve; ``u0``: its initial guess (returned when the solve made things worse or is not
    finite); ``hops``: nodes still whole periods off the coarse level (:func:`repair_peak_hopping`); ``period``:
    RF period (mm) of the hop check (None: no check, single-row images); ``global_ncc``: the pyramid's global
    envelope NCC (None without a pyramid).  Fails (``success=False``, a note each) when the solve is not finite,
    explains less of the image than its start, the NCC after is below :data:`MIN_NCC`, peak hopping remains,
    more than :data:`MAX_POOR_FRACTION` of the elements do not match, more than :data:`MAX_HOPPED_FRACTION` of
    them match the envelope better one period off, or a decorrelated pair has more than
    :data:`MAX_POOR_FRACTION_DECORRELATED` of its elements not matching.

    Never worse than the start (:func:`_explains_less`): the result may explain up to :data:`PSI_SLACK` (RF) or
    :data:`ENVELOPE_PSI_SLACK` (``envelope``: envelope / B-mode frames) less of the image than its start when
    eq:objf fell.

    ``groups`` (n_elements,) int: a refined mesh's unrefined parent cells (:func:`femreg.refine.parent_cells`).
    The fractions then count those cells (the NCC and the hop gain over each cell's pixels at the refined u), so
    that the same limits hold on the refined result as on the unrefined one: an element of a quarter of the
    pixels is noisier (per element, 3 % of the elements of a correct result refined to a quarter read one
    period off: robustness benchmark, soft inclusion at 4 % under the paper's probe; on the parent cells it
    passes).
    The maps (``quality``, ``hop_gain``) stay per element."""
    notes = []
    data = sol.data
    n_el = sol.mesh.t.shape[1]
    # each evaluation of the data term at a new u is a warp of I_2 (it caches the residual of the last u only):
    # I_2 at u = 0 without the cache, psi at the start from the solve, psi at the result (usually cached)
    zero = np.zeros(len(u0))
    w0 = data.warped_moving(zero)
    psi_zero = 0.5 * float(np.dot(data.w * (w0 - data.ref_values), w0 - data.ref_values))
    ncc0 = ncc(w0, data.ref_values)
    psi_start = sol.psi_start if sol.start is u0 else data.energy(u0)
    psi_final = data.energy(sol.u)
    success, u_out = True, sol.u
    if np.any(sol.u) and psi_zero <= psi_final:
        u_out, psi_final = zero, psi_zero                  # no motion explains it as well
    if not np.all(np.isfinite(sol.u)):
        success, u_out = False, u0
        notes.append("the solve produced non-finite values; returning the initial guess")
    elif _explains_less(sol, u0, u_out, psi_start, psi_final, envelope):
        success, u_out = False, u0
        notes.append(f"the result explains less of the image than its start (psi {psi_final:.4g} > "
                     f"{psi_start:.4g}); returning the initial guess")
    ncc1 = ncc(data.residual(u_out) + data.ref_values, data.ref_values)
    if not (np.isfinite(ncc1) and ncc1 >= MIN_NCC):
        success = False
        notes.append(f"the images do not match: NCC after {ncc1:.3f} < {MIN_NCC}")
    if hops.any():
        # the RF and envelope levels still disagree by whole periods after the repair: one of them sits in the
        # wrong basin (in-plane rotation beyond what the speckle keeps correlated: 2 of 2 such results wrong by
        # 185-210 % total strain error; no correct result of the benchmarks or the in vivo pairs has any)
        success = False
        notes.append(f"peak hopping remains at {int(np.count_nonzero(hops))} of {hops.size} nodes (they differ "
                     f"from the coarse level by whole RF periods)")
    quality = element_ncc(data, u_out, n_el)
    poor = poor_fraction(quality if groups is None else element_ncc(data, u_out, n_el, groups=groups))
    if poor > MAX_POOR_FRACTION:
        success = False
        notes.append(f"{poor:.0%} of the elements do not match (element NCC < {MIN_NCC}; see the quality map)")
    elif poor > 0.1:
        notes.append(f"{poor:.0%} of the elements match poorly (element NCC < {MIN_NCC}; see the quality map)")
    # peak hopping seen in the images themselves (every strategy; the node test above needs a coarser level)
    gain = None
    if period is not None:
        gain = hop_gain(data, u_out, n_el, period, shape, spacing)
        hopped = hopped_fraction(gain if groups is None
                                 else hop_gain(data, u_out, n_el, period, shape, spacing, groups=groups))
        if hopped > MAX_HOPPED_FRACTION:
            success = False
            notes.append(hop_note(hopped, period))
    decorrelated = global_ncc is not None and global_ncc < ROTATION_SCAN_NCC
    if decorrelated and poor > MAX_POOR_FRACTION_DECORRELATED and success:
        success = False
        notes.append(f"on a decorrelated pair more than {MAX_POOR_FRACTION_DECORRELATED:.0%} of the elements not "
                     f"matching mark a wrong result")
    if decorrelated and (not success or poor > 0.1):
        # the speckle decorrelated between the frames (rotation, strain of several percent): say what works
        notes.append(f"the pair is strongly decorrelated (global envelope NCC {global_ncc:.2f}); register "
                     f"closer frames, or the whole sequence with track")
    return Check(success=success, u=u_out, notes=notes, ncc_before=ncc0, ncc_after=ncc1, quality=quality,
                 hop_gain=gain)


def frame_flag(res, min_ncc) -> str:
    """Why a tracked frame is flagged (:func:`femreg.track`, frames and volumes alike), '' for a good one: its
    registration failed its own check, or its NCC after is below ``min_ncc`` (None: no NCC limit)."""
    if not res.success:
        return f"registration failed: {res.message.removeprefix('FAILED: ')}"
    if min_ncc is not None and not (np.isfinite(res.ncc_after) and res.ncc_after >= min_ncc):
        return f"low NCC after registration ({res.ncc_after:.3f} < {min_ncc})"
    return ""


TAINT_PREFIX = "FAILED: accumulated through frame "
#: Between a tainted frame's reason and its own increment's message (:func:`mark_tainted`).
OWN_INCREMENT = "; this frame's own increment: "


def mark_tainted(res, k: int, why: str) -> None:
    """Frame 0 -> j > ``k`` adds frame ``k``'s flagged increment (eq:IR): its field is no better than that one,
    whatever its own increment's check says, so it is failed too (plot, measure and invert then say so)."""
    own = res.message.removeprefix("FAILED: ")
    own = own if res.success else f"FAILED: {own}"
    res.success = False
    why = why.split("; ")[0]           # its reason; what it left out is this frame's too, said below
    res.message = f"{TAINT_PREFIX}{k}, whose increment was flagged ({why}){OWN_INCREMENT}{own}"


def own_flag(res, flag: str, min_ncc) -> str:
    """The flag of frame k's own increment, without the one :func:`mark_tainted` added (a loaded frame too)."""
    head, sep, own = res.message.partition(OWN_INCREMENT)
    if not (sep and head.startswith(TAINT_PREFIX)):
        return flag
    from types import SimpleNamespace

    # frame_flag of the increment as it was before mark_tainted: its success and message, the same NCC
    return frame_flag(SimpleNamespace(success=not own.startswith("FAILED: "), message=own, ncc_after=res.ncc_after),
                      min_ncc)


def retry_flagged(register_from, previous, fresh_start, fresh: bool, min_ncc, k: int):
    """Frame ``k``'s increment of an accumulated track (:func:`femreg.track`, frames and volumes alike), where the
    previous increment's solution can start a whole RF period off (a freehand loop's compression per frame
    varies).  ``register_from(start)`` registers the pair from ``start`` and returns (frame 0 -> k result, the
    increment); it is called from ``previous`` unless ``fresh``, and when that result is flagged
    (:func:`frame_flag`) again from ``fresh_start`` (the registration's own start), the better kept
    (:func:`keep_retry`).  Returns (result, increment, retry note: '' when it was not retried)."""
    res, inc = register_from(fresh_start if fresh else previous)
    # a start the registration already replaced by the fresh one (femreg.initial.previous_or_fresh): no retry
    why = "" if fresh or res.started_afresh else frame_flag(res, min_ncc)
    if not why:
        return res, inc, ""
    again, inc_again = register_from(fresh_start)
    return keep_retry(res, inc, why, again, inc_again, min_ncc, k)


def keep_retry(res, inc, why: str, again, inc_again, min_ncc, k: int):
    """Of frame ``k``'s increment started from the previous one (``res``, ``inc``; flagged for ``why``) and the
    one registered again from a fresh start (``again``, ``inc_again``): the fresh one unless it is flagged too,
    then the one with the higher NCC after registration.  Returns (result, increment, retry note); the note is
    added to the kept result's message."""
    why = why.split("; ")[0]
    again_flag = frame_flag(again, min_ncc)
    if not again_flag:
        kept, k_inc, which = again, inc_again, "kept the fresh start"
    else:
        a, b = again.ncc_after, res.ncc_after
        fresh_better = np.isfinite(a) and not (np.isfinite(b) and b > a)
        kept, k_inc = (again, inc_again) if fresh_better else (res, inc)
        which = (f"the fresh start flagged too ({again_flag.split('; ')[0]}): kept the "
                 f"{'fresh start' if fresh_better else 'start from the previous increment'} (NCC after {a:.3f} "
                 f"fresh, {b:.3f} from the previous increment)")
    note = (f"retried from a fresh start: the increment started from frame {k - 1}'s was flagged ({why}); "
            f"{which}")
    kept.message = f"{kept.message}; {note}" if kept.message else note
    return kept, k_inc, note


def summarise_flags(flags) -> str:
    """The flags of a run's frames (1-based) in one line: each frame's own reason, and the frames flagged only for
    adding an earlier flagged increment (:func:`mark_tainted`) named once, not each with that reason again."""
    parts, tainted, source = [], [], None
    for k, f in enumerate(flags, start=1):
        if not f:
            continue
        head, sep, own = f.partition(OWN_INCREMENT)
        if sep and TAINT_PREFIX.removeprefix("FAILED: ") in head:
            tainted.append(k)
            source = source or head.split(TAINT_PREFIX.removeprefix("FAILED: "))[1].split(",")[0]
            if own.startswith("FAILED: "):
                parts.append(f"frame {k}: registration failed: {own.removeprefix('FAILED: ')}")
        else:
            parts.append(f"frame {k}: {f}")
    if tainted:
        parts.append(f"frame{'s' if len(tainted) > 1 else ''} {', '.join(map(str, tainted))}: accumulated through "
                     f"frame {source}'s flagged increment")
    return "; ".join(parts)
