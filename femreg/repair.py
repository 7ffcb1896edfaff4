"""Check and repair stage of :func:`femreg.register`: per-element quality, peak-hopping detection and repair,
and the rule that a result never explains less of the image than its start.

Peak hopping: from a start more than about a quarter of the RF period off, Gauss-Newton on RF converges to the
neighbouring correlation peak, one period T off in u_x (bands of +-T in u_x, stripes in e_xx).  It is detected
node by node: u_x minus a robust reference (the coarser level's field plus the local median of the difference,
or the local median of u_x itself when there is no coarser level) is more than :data:`HOP_FRACTION` of T away
from zero.  Such nodes are reseeded by whole periods towards the reference and the solve is repeated.

Quality map: the NCC of reference and warped moving image over the pixels of each element (1 = perfect match;
speckle decorrelation lowers it smoothly, a hop or a failure drops it towards 0).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from . import _kernels
from .mesh import tensor_structure

__all__ = ["element_ncc", "pixel_values", "hop_nodes", "reseed", "poor_fraction", "HOP_FRACTION", "MIN_NCC",
           "MAX_POOR_FRACTION"]

#: A node is hopping when |u_x - reference| exceeds this fraction of the RF period.
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


def pixel_values(quad, v) -> np.ndarray:
    """Nodal scalar ``v`` (n_nodes,) at the quadrature pixels of ``quad`` (:class:`femreg.pixels.PixelQuadrature`),
    (n_pixels,).  On a tensor mesh by two 1D interpolations of the node grid (rows, then columns), without the
    per-pixel shape-function arrays (0.4 s on a paper-size image)."""
    loc = quad.location
    gr = loc.grid
    if gr is None:
        return quad.P @ v
    Vg = np.asarray(v, float)[quad.locator.node_grid]                      # (nx, ny)
    i, X, j, Y = gr["i"], gr["X"], gr["j"], gr["Y"]
    A = (1.0 - X)[:, None] * Vg[i] + X[:, None] * Vg[i + 1]                  # (nr, ny)
    return ((1.0 - Y)[None, :] * A[:, j] + Y[None, :] * A[:, j + 1]).ravel()


def _pixel_elements(quad) -> np.ndarray:
    """Element of each quadrature pixel (n_pixels,); on tensor meshes from the separable grid description."""
    gr = quad.location.grid
    if gr is None:
        return quad.location.element
    cell = quad.locator.tensor[2]
    return cell[gr["i"][:, None], gr["j"][None, :]].ravel()


def element_ncc(data, u, n_elements: int) -> np.ndarray:
    """NCC of reference and warped moving image over each element's pixels, (n_elements,); NaN for elements
    with fewer than 4 pixels.  ``data`` is the :class:`femreg.data_term.SSDTerm` of the solve."""
    a = data.ref_values
    b = data.residual(u) + a
    gr = data.quad.location.grid
    if gr is not None and _kernels.use_compiled() and np.all(np.diff(gr["i"]) >= 0) and np.all(np.diff(gr["j"]) >= 0):
        # tensor mesh: pixel rows x columns of each element are consecutive; one compiled pass per moment
        rseg = np.cumsum(np.diff(gr["i"], prepend=gr["i"][0]) > 0)
        cseg = np.cumsum(np.diff(gr["j"], prepend=gr["j"][0]) > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            qb, cb = _kernels.block_ncc(np.ascontiguousarray(a), np.ascontiguousarray(b), rseg, cseg,
                                        int(rseg[-1]) + 1, int(cseg[-1]) + 1)
        cell = data.quad.locator.tensor[2][np.unique(gr["i"])[:, None], np.unique(gr["j"])[None, :]]
        q = np.full(n_elements, np.nan)
        cnt = np.zeros(n_elements)
        q[cell.ravel()], cnt[cell.ravel()] = qb.ravel(), cb.ravel()
        q[cnt < 4] = np.nan
        return q
    e = _pixel_elements(data.quad)
    cnt = np.bincount(e, minlength=n_elements).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma = np.bincount(e, a, n_elements) / cnt
        mb = np.bincount(e, b, n_elements) / cnt
        da, db = a - ma[e], b - mb[e]
        sab = np.bincount(e, da * db, n_elements)
        saa = np.bincount(e, da * da, n_elements)
        sbb = np.bincount(e, db * db, n_elements)
        q = sab / np.sqrt(saa * sbb)
    q[cnt < 4] = np.nan
    return q


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
        xs, ys, _ = ts
        ix = np.searchsorted(xs, mesh.p[0])
        iy = np.searchsorted(ys, mesh.p[1])
        G = np.empty((xs.size, ys.size))
        G[ix, iy] = values
        return ndimage.median_filter(G, size=size, mode="nearest")[ix, iy]
    from .pixels import logical_grid

    lg = logical_grid(mesh)              # a moved tensor mesh (femreg.track): the same filter on its node grid
    if lg is not None:
        G = lg[0]
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

    ``reference`` (n_nodes,) is the coarser level's u_x at the nodes (None: the local median of ``ux``)."""
    ux = np.asarray(ux, float)
    if reference is None:
        d = ux - _node_median(mesh, ux)
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
