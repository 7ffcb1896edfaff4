"""Mesh floor of adaptive mesh types: graded tensor quads (femreg's), quadtree quads with constrained hanging
nodes, and conforming triangles refined by scikit-fem -- error against nodes at equal marking.

The *mesh floor* is the strain error a mesh keeps even when the registration is perfect: the exact displacement
at the mesh's nodes, its strain recovered as femreg's (the mean of the element-centre strains around each node,
:func:`femreg.fields.recovered_strains`, interpolated over the element), scored against the exact strain.  It is
the "exact u on R_P_sigma's mesh" row of ``benchmarks/inclusion_sizes.py``, with the robustness benchmark's
metric (:func:`benchmarks.robustness.errors`: total strain error ``||e_h - e_t|| / ||e_t||`` with
``e:e = e_xx^2 + e_yy^2 + 2 e_xy^2``, over the ROI samples of :func:`benchmarks.robustness.roi_slices`).  The
image term and the regulariser play no part: this measures what each mesh type can hold, not what a registration
on it recovers.

Mesh types, all refined from the same uniform base mesh (:func:`femreg.mesh.roi_mesh`, ``element_size`` 1.4 mm,
the default 1 mm margin):

* ``tensor``: femreg's graded tensor mesh; a marked element splits its whole row and whole column in two
  (:func:`femreg.refine.refine_tensor_mesh`, breaks on pixel-cell boundaries, at least 2 pixels and ``min_size``);
* ``tensor-dir``: the same mesh, marked by direction as femreg's jump indicator does (axial variation marks rows,
  lateral variation columns): the Doerfler marking runs on row and column scores, each the sum over the row
  (column) of what halving its elements along depth (laterally) takes off their floor error
  (:func:`directional_scores`, :func:`box_energy`: the raw element gradient, so that an element's score is its
  own, integrated from the displacement, exact for a band's step);
* ``quadtree``: marked elements split into 4, 2:1 balanced across edges; a hanging node (the midpoint of a coarse
  element's edge) is constrained to the mean of that edge's end nodes, so the bilinear field stays continuous
  (:class:`QuadTree`); nodes counted are the free ones;
* ``tri``: the base quads cut into 2 triangles each (``MeshTri1.init_tensor``), marked triangles refined by
  scikit-fem's conforming red-green-blue refinement (``MeshTri1.refined(marked)``), P1 elements, strain recovered
  the same way (mean of the constant element strains around each node, interpolated linearly).

Marking, the same for ``tensor``, ``quadtree`` and ``tri`` (an oracle, not femreg's data-driven marking): the
per-element floor error ``eta_K^2 = int_K |e_h - e_t|^2`` (recovered strain, shear counted twice; 3-point Gauss on
3 x 3 sub-boxes of a quad, scikit-fem's degree-13 rule on a triangle: the true strain steps inside an element),
Doerfler / bulk marking with fraction ``theta`` (the fewest elements holding
``theta`` of the total ``sum eta_K^2``).  An element is split only if its halves stay at least ``min_size``
(axial, lateral) mm: in the ``pixel`` regime 0.15 mm axially (femreg's :data:`femreg.refine.DEEP_REFINEMENT`) and
2 lateral pixels laterally (the finest column femreg's tensor split allows); the ``free`` regime lifts it
(midpoint splits, no pixel grid, no size limit).  The ``tensor`` mesh is refined ``--steps`` times; the other
types go on (at most 3 x ``--steps``) until they reach the tensor mesh's last floor or stall.

Per case x mesh type x step: free nodes, elements, smallest element (axial x lateral mm), the floor total strain
error % over the ROI (recovered strain, and the raw element gradient as a plain FE post-processing would), and
the error inside the ring ``0.8 R < |x - c| < 1.2 R`` around an inclusion (for the shear band: within one band
thickness of its centre).

Run: ``python benchmarks/mesh_types.py [--cases word,...] [--steps 5] [--theta 0.5] [--regimes pixel,free]
[--out out/mesh_types] [--plot docs/mesh_types.png] [--from-json out/mesh_types/results.json]``; 9 min 20 s
on one thread of a shared 2-core machine, 0.34 GB (the FE inclusions are cached on disk by
:func:`forward.elasticity.cached_solve`).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import Case, errors, roi_slices  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES  # noqa: E402

#: target size (mm) of the uniform base mesh every mesh type starts from
BASE_ELEMENT_MM = 1.4
#: smallest axial element (mm) a split may leave (femreg.refine.DEEP_REFINEMENT's min_size[0])
MIN_AXIAL_MM = 0.15
MESH_TYPES = ("tensor", "tensor-dir", "quadtree", "tri")
_G3 = np.array([0.5 - np.sqrt(0.15), 0.5, 0.5 + np.sqrt(0.15)])
_W3 = np.array([5.0, 8.0, 5.0]) / 18.0
#: sub-intervals per direction of the oracle's composite Gauss rule on quads: the true strain steps inside an
#: element (an inclusion's rim, a band's faces), which 3 x 3 points alone sample too coarsely to rank elements
ORACLE_SUB = 3
#: degree of the oracle's rule on triangles (scikit-fem's, 37 points at 13), about as many points per area as
#: the quads' composite rule on their two triangles
TRI_ORACLE_DEGREE = 13


def composite_rule(m=None):
    """Points (k,) in [0, 1] and weights (k,) (sum 1): 3-point Gauss on ``m`` (default :data:`ORACLE_SUB`) equal
    sub-intervals."""
    m = ORACLE_SUB if m is None else int(m)
    x = ((np.arange(m)[:, None] + _G3[None, :]) / m).ravel()
    return x, np.tile(_W3, m) / m



def _inc(kind, radius):
    return lambda: F.Inclusion(kind, "plane-strain", 0.01, radius_mm=radius)


#: imaged regions as ``benchmarks/inclusion_sizes.py`` (r 3 mm: 30 x 30 mm from 5 mm; r 8 mm: 35 x 35 mm from
#: 2.5 mm, paper probe) and ``benchmarks/shear_bands.py`` (1 mm band 15 mm deep, L7)
CASES = [
    Case("stiff_r3_1pc_paper", _inc("stiff", 3.0), "paper", (30, 30), 20, top_mm=5.0),
    Case("soft_r3_1pc_paper", _inc("soft", 3.0), "paper", (30, 30), 20, top_mm=5.0),
    Case("stiff_r8_1pc_paper", _inc("stiff", 8.0), "paper", (35, 35), 25, top_mm=2.5),
    Case("soft_r8_1pc_paper", _inc("soft", 8.0), "paper", (35, 35), 25, top_mm=2.5),
    Case("band1_s0.15_d15_L7", lambda: F.ShearBand(15.0, 1.0, 0.15, 0.01), "L7", (30, 30), 30),
]


# ----------------------------------------------------------------------------------------------------------------
# Rectangle meshes (tensor and quadtree): leaves in an integer lattice over the base tensor grid
# ----------------------------------------------------------------------------------------------------------------

class QuadTree:
    """Axis-aligned quads refined from a tensor base grid by splitting leaves into 4, 2:1 balanced across edges.

    Leaves are boxes ``[X0, X1] x [Y0, Y1]`` in an integer lattice: base break ``i`` sits at ``i * 2**depth``, so
    every midpoint is exact; :meth:`physical` maps lattice to mm piecewise linearly inside each base interval.
    ``xs`` (n_x,), ``ys`` (n_y,) base breaks (mm, axial / lateral).
    """

    def __init__(self, xs, ys, depth: int = 12):
        self.xs, self.ys, self.depth = np.asarray(xs, float), np.asarray(ys, float), int(depth)
        s = 1 << self.depth
        i, j = np.meshgrid(np.arange(self.xs.size - 1), np.arange(self.ys.size - 1), indexing="ij")
        self.boxes = np.column_stack([i.ravel() * s, (i.ravel() + 1) * s, j.ravel() * s, (j.ravel() + 1) * s])
        self._build()

    # -- geometry -------------------------------------------------------------------------------------------
    def _phys(self, X, breaks):
        s = 1 << self.depth
        X = np.asarray(X, np.int64)
        b = np.minimum(X // s, breaks.size - 2)
        return breaks[b] + (breaks[b + 1] - breaks[b]) * (X - b * s) / s

    def physical(self, X, Y):
        """mm coordinates of lattice points."""
        return self._phys(X, self.xs), self._phys(Y, self.ys)

    def _key(self, X, Y):
        return np.asarray(X, np.int64) * (1 << 40) + np.asarray(Y, np.int64)

    def _build(self):
        B = self.boxes
        # corners in skfem MeshQuad1.init_tensor order: (x0,y0), (x0,y1), (x1,y1), (x1,y0)
        cx = np.stack([B[:, 0], B[:, 0], B[:, 1], B[:, 1]])
        cy = np.stack([B[:, 2], B[:, 3], B[:, 3], B[:, 2]])
        keys, inv = np.unique(self._key(cx, cy).ravel(), return_inverse=True)
        self.keys = keys
        self.t = inv.reshape(4, -1)
        X, Y = keys >> 40, keys & ((1 << 40) - 1)
        self.p = np.vstack(self.physical(X, Y))
        # hanging nodes: an existing node at the midpoint of a leaf's edge (2:1 balance: only midpoints)
        hang, pa, pb, length = [], [], [], []
        for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
            ka, kb = keys[self.t[a]], keys[self.t[b]]
            mx = ((ka >> 40) + (kb >> 40)) // 2
            my = ((ka & ((1 << 40) - 1)) + (kb & ((1 << 40) - 1))) // 2
            km = self._key(mx, my)
            pos = np.clip(np.searchsorted(keys, km), 0, keys.size - 1)
            found = keys[pos] == km
            hang.append(pos[found])
            pa.append(self.t[a][found])
            pb.append(self.t[b][found])
            length.append(np.abs(ka - kb)[found])
        h, a_, b_, L = (np.concatenate(v) for v in (hang, pa, pb, length))
        h, first = np.unique(h, return_index=True)
        order = np.argsort(-L[first], kind="stable")   # longest coarse edges first: their ends are settled first
        self.hanging = np.column_stack([h, a_[first], b_[first]])[order]
        free = np.ones(self.p.shape[1], bool)
        free[self.hanging[:, 0]] = False
        self.free = free

    # -- refinement ------------------------------------------------------------------------------------------
    def size(self):
        """(n_el, 2) element sizes (axial, lateral) mm."""
        x0, y0 = self.physical(self.boxes[:, 0], self.boxes[:, 2])
        x1, y1 = self.physical(self.boxes[:, 1], self.boxes[:, 3])
        return np.column_stack([x1 - x0, y1 - y0])

    def _split(self, sel):
        B = self.boxes
        keep, S = B[~sel], B[sel]
        mx, my = (S[:, 0] + S[:, 1]) // 2, (S[:, 2] + S[:, 3]) // 2
        kids = np.concatenate([np.column_stack([S[:, 0], mx, S[:, 2], my]),
                               np.column_stack([mx, S[:, 1], S[:, 2], my]),
                               np.column_stack([S[:, 0], mx, my, S[:, 3]]),
                               np.column_stack([mx, S[:, 1], my, S[:, 3]])])
        self.boxes = np.concatenate([keep, kids])

    def refine(self, marked):
        """Split the ``marked`` leaves (bool (n_el,) or indices) into 4, then split leaves until every edge holds
        at most one hanging node (2:1 balance)."""
        sel = np.zeros(len(self.boxes), bool)
        sel[np.asarray(marked)] = True
        if (self.boxes[sel, 1] - self.boxes[sel, 0]).min(initial=4) < 2:
            raise ValueError("quadtree lattice too shallow for this split")
        self._split(sel)
        while True:
            B = self.boxes
            corners = np.unique(np.concatenate([self._key(B[:, c], B[:, d]) for c in (0, 1) for d in (2, 3)]))
            viol = np.zeros(len(B), bool)
            for (xa, ya), (xb, yb) in ((((0, 2)), (0, 3)), ((1, 2), (1, 3)), ((0, 2), (1, 2)), ((0, 3), (1, 3))):
                for q in (1, 3):        # quarter points of an edge: a neighbour two levels finer
                    qx = (B[:, xa] * (4 - q) + B[:, xb] * q) // 4
                    qy = (B[:, ya] * (4 - q) + B[:, yb] * q) // 4
                    km = self._key(qx, qy)
                    pos = np.clip(np.searchsorted(corners, km), 0, corners.size - 1)
                    viol |= corners[pos] == km
            if not viol.any():
                break
            self._split(viol)
        self._build()

    # -- fields ----------------------------------------------------------------------------------------------
    def constrain(self, values):
        """Nodal values (n_nodes, k) with every hanging node set to the mean of its coarse edge's end nodes (in
        order, so chained constraints resolve); returns a copy."""
        v = np.array(values, float, copy=True)
        for h, a, b in self.hanging:
            v[h] = 0.5 * (v[a] + v[b])
        return v

    def interpolant(self, displacement):
        """Constrained nodal interpolant (n_nodes, 2) mm of ``displacement`` (callable (n, 2) mm -> (n, 2) mm):
        exact at the free nodes, each hanging node the mean of its coarse edge's ends."""
        u = np.asarray(displacement(self.p.T), float)
        return self.constrain(u)


def rect_recovered(p, t, u, hanging=None):
    """femreg's recovered strain (n_nodes, 3) on a quad mesh (:func:`femreg.fields.element_strains`,
    :func:`femreg.fields.nodal_average`), hanging nodes then constrained as the displacement; ``u`` (n_nodes, 2)."""
    from femreg.fields import element_strains, nodal_average

    e = element_strains(p, t, np.asarray(u, float).ravel())
    s = nodal_average(t, e, p.shape[1])
    if hanging is not None:
        for h, a, b in hanging:
            s[h] = 0.5 * (s[a] + s[b])
    return s, e


def _rect_bilinear(p, t, vals, el, X, Y):
    """Bilinear value of nodal ``vals`` (n_nodes, k) at points (X, Y) in rectangles ``el``; corners in
    MeshQuad1.init_tensor order."""
    c = t[:, el]
    x0, x1 = p[0, c[0]], p[0, c[2]]
    y0, y1 = p[1, c[0]], p[1, c[2]]
    r = ((X - x0) / (x1 - x0))[:, None]
    s = ((Y - y0) / (y1 - y0))[:, None]
    return ((1 - r) * (1 - s) * vals[c[0]] + (1 - r) * s * vals[c[1]] + r * s * vals[c[2]] + r * (1 - s) * vals[c[3]])


def _rect_grad(p, t, u, el, X, Y):
    """Raw strain [exx, eyy, exy] (n, 3) of the bilinear ``u`` (n_nodes, 2) at points in rectangles ``el``."""
    c = t[:, el]
    x0, x1 = p[0, c[0]], p[0, c[2]]
    y0, y1 = p[1, c[0]], p[1, c[2]]
    r = ((X - x0) / (x1 - x0))[:, None]
    s = ((Y - y0) / (y1 - y0))[:, None]
    dx = ((1 - s) * (u[c[3]] - u[c[0]]) + s * (u[c[2]] - u[c[1]])) / (x1 - x0)[:, None]
    dy = ((1 - r) * (u[c[1]] - u[c[0]]) + r * (u[c[2]] - u[c[3]])) / (y1 - y0)[:, None]
    return np.column_stack([dx[:, 0], dy[:, 1], 0.5 * (dy[:, 0] + dx[:, 1])])


def _locate_rects(p, t, xg, yg):
    """Element index (len(xg), len(yg)) of every sample of the tensor grid xg x yg (sorted) in a rectangle mesh."""
    out = np.full((xg.size, yg.size), -1, np.int64)
    x0, x1 = p[0, t[0]], p[0, t[2]]
    y0, y1 = p[1, t[0]], p[1, t[2]]
    i0, i1 = np.searchsorted(xg, x0, "left"), np.searchsorted(xg, x1, "right")
    j0, j1 = np.searchsorted(yg, y0, "left"), np.searchsorted(yg, y1, "right")
    for k in np.flatnonzero((i1 > i0) & (j1 > j0)):
        out[i0[k]:i1[k], j0[k]:j1[k]] = k
    return out


# ----------------------------------------------------------------------------------------------------------------
# Triangles (P1)
# ----------------------------------------------------------------------------------------------------------------

def tri_strains(p, t, u):
    """Constant strain [exx, eyy, exy] (n_el, 3) of P1 ``u`` (n_nodes, 2) on triangles ``t`` (3, n_el)."""
    x, y = p[0, t], p[1, t]
    det = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    # gradients of the barycentric functions
    gx = np.stack([y[1] - y[2], y[2] - y[0], y[0] - y[1]]) / det
    gy = np.stack([x[2] - x[1], x[0] - x[2], x[1] - x[0]]) / det
    ux, uy = u[t, 0], u[t, 1]
    dux_dx, dux_dy = np.sum(gx * ux, 0), np.sum(gy * ux, 0)
    duy_dx, duy_dy = np.sum(gx * uy, 0), np.sum(gy * uy, 0)
    return np.column_stack([dux_dx, duy_dy, 0.5 * (dux_dy + duy_dx)])


def _tri_bary(p, t, el, X, Y):
    x, y = p[0, t[:, el]], p[1, t[:, el]]
    det = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    l1 = ((X - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (Y - y[0])) / det
    l2 = ((x[1] - x[0]) * (Y - y[0]) - (X - x[0]) * (y[1] - y[0])) / det
    return np.column_stack([1 - l1 - l2, l1, l2])


# ----------------------------------------------------------------------------------------------------------------
# One mesh state: nodal interpolant, recovered strain, per-element oracle error, ROI floor
# ----------------------------------------------------------------------------------------------------------------

def _frob2(d):
    """|d|^2 with the shear counted twice, d (..., 3) [exx, eyy, exy]."""
    return d[..., 0] ** 2 + d[..., 1] ** 2 + 2 * d[..., 2] ** 2


class MeshState:
    """Nodal interpolant of the exact field on one mesh (``kind`` "rect" or "tri") and its floor."""

    def __init__(self, kind, p, t, field, hanging=None, free=None):
        self.kind, self.p, self.t, self.field = kind, np.asarray(p, float), np.asarray(t), field
        self.hanging = hanging
        u = np.asarray(field.displacement(self.p.T), float)
        if kind == "rect":
            u = u.copy()
            if hanging is not None:
                for h, a, b in hanging:
                    u[h] = 0.5 * (u[a] + u[b])
            self.s, _ = rect_recovered(self.p, self.t, u, hanging)
        else:
            from femreg.fields import nodal_average

            self.s = nodal_average(self.t, tri_strains(self.p, self.t, u), self.p.shape[1])
        self.u = u
        self.n_free = int(self.p.shape[1] if free is None else np.count_nonzero(free))

    def eta2(self):
        """Per-element ``int_K |e_h - e_t|^2`` (n_el,), recovered strain (the oracle of the marking)."""
        if self.kind == "rect":
            g, w = composite_rule()
            c = self.t
            x0, x1 = self.p[0, c[0]], self.p[0, c[2]]
            y0, y1 = self.p[1, c[0]], self.p[1, c[2]]
            out = np.zeros(c.shape[1])
            for a in range(g.size):
                for b in range(g.size):
                    X, Y = x0 + g[a] * (x1 - x0), y0 + g[b] * (y1 - y0)
                    el = np.arange(c.shape[1])
                    sh = _rect_bilinear(self.p, self.t, self.s, el, X, Y)
                    st = self.field.strain(np.column_stack([X, Y]))
                    out += w[a] * w[b] * _frob2(sh - st)
            return out * (x1 - x0) * (y1 - y0)
        from skfem.quadrature import get_quadrature
        from skfem.refdom import RefTri

        Xr, W = get_quadrature(RefTri, TRI_ORACLE_DEGREE)
        x, y = self.p[0, self.t], self.p[1, self.t]
        area = 0.5 * np.abs((x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]))
        out = np.zeros(self.t.shape[1])
        for q in range(W.size):
            lam = np.array([1 - Xr[0, q] - Xr[1, q], Xr[0, q], Xr[1, q]])
            X, Y = lam @ x, lam @ y
            sh = sum(lam[k] * self.s[self.t[k]] for k in range(3))
            out += W[q] * _frob2(sh - self.field.strain(np.column_stack([X, Y])))
        return out * 2 * area        # W sums to 1/2, the reference triangle's area

    def on_samples(self, xg, yg):
        """u, recovered strain and raw element strain on the tensor grid xg x yg: dict of (nx, ny) arrays."""
        X, Y = np.meshgrid(xg, yg, indexing="ij")
        X, Y = X.ravel(), Y.ravel()
        if self.kind == "rect":
            el = _locate_rects(self.p, self.t, xg, yg).ravel()
            if np.any(el < 0):
                raise ValueError("ROI samples outside the mesh")
            u = _rect_bilinear(self.p, self.t, self.u, el, X, Y)
            s = _rect_bilinear(self.p, self.t, self.s, el, X, Y)
            ee = _rect_grad(self.p, self.t, self.u, el, X, Y)
        else:
            from matplotlib.tri import Triangulation

            # matplotlib's trapezoid map: scikit-fem's element_finder allocates (n_points, n_el) on big meshes
            el = Triangulation(self.p[0], self.p[1], self.t.T).get_trifinder()(X, Y)
            if np.any(el < 0):
                raise ValueError("ROI samples outside the mesh")
            lam = _tri_bary(self.p, self.t, el, X, Y)
            u = sum(lam[:, k:k + 1] * self.u[self.t[k, el]] for k in range(3))
            s = sum(lam[:, k:k + 1] * self.s[self.t[k, el]] for k in range(3))
            ee = tri_strains(self.p, self.t, self.u)[el]
        sh = (xg.size, yg.size)
        out = {"ux": u[:, 0], "uy": u[:, 1], "exx": s[:, 0], "eyy": s[:, 1], "exy": s[:, 2]}
        out = {k: v.reshape(sh) for k, v in out.items()}
        out["element"] = {"ux": out["ux"], "uy": out["uy"], "exx": ee[:, 0].reshape(sh),
                          "eyy": ee[:, 1].reshape(sh), "exy": ee[:, 2].reshape(sh)}
        return out

    def min_size(self):
        """Smallest element extent (axial, lateral) mm."""
        x, y = self.p[0, self.t], self.p[1, self.t]
        return float(np.min(x.max(0) - x.min(0))), float(np.min(y.max(0) - y.min(0)))


def doerfler(eta2, theta, eligible):
    """Bool (n_el,): the fewest eligible elements whose ``eta2`` sum reaches ``theta`` of the eligible total."""
    e = np.where(eligible, eta2, 0.0)
    order = np.argsort(-e, kind="stable")
    c = np.cumsum(e[order])
    n = int(np.searchsorted(c, theta * c[-1]) + 1) if c[-1] > 0 else 0
    out = np.zeros(e.size, bool)
    out[order[:n]] = True
    return out & eligible


# ----------------------------------------------------------------------------------------------------------------
# The study
# ----------------------------------------------------------------------------------------------------------------

def case_geometry(case):
    """(shape, spacing, origin) of the case's image (as :func:`forward.pairs.make_pair` renders it)."""
    from forward.ultrasound import ImagingGrid

    g = ImagingGrid.centred(depth_mm=case.size_mm[0], width_mm=case.size_mm[1], spacing=PROBES[case.probe].spacing,
                            top_mm=case.top_mm)
    return g.shape, g.spacing, g.origin


def _scores(state, xg, yg, t_roi, zone):
    """Floor total strain error (fractions) over the ROI samples xg x yg: recovered strain, raw element strain (the
    robustness metric, :func:`benchmarks.robustness.errors`), and recovered strain inside ``zone`` (bool)."""
    g = state.on_samples(xg, yg)
    ident = (slice(None), slice(None))
    e_rec = errors(g, t_roi, ident, 1.0)["e"]
    e_el = errors(g["element"], t_roi, ident, 1.0)["e"]
    num = sum(w * np.sum((g[k][zone] - t_roi[k][zone]) ** 2) for k, w in (("exx", 1), ("eyy", 1), ("exy", 2)))
    den = sum(w * np.sum(t_roi[k][zone] ** 2) for k, w in (("exx", 1), ("eyy", 1), ("exy", 2)))
    return e_rec, e_el, float(np.sqrt(num / den))




#: sub-cells per direction of :func:`box_energy`'s cross term
BOX_SUB = 4


def box_energy(field, x0, x1, y0, y1):
    """``int_K |e_h|^2 - 2 e_h : e_t`` (n,) for the bilinear interpolant ``u_h`` of the exact ``u`` on each box
    ``K = [x0, x1] x [y0, y1]`` (mm, arrays (n,)), ``e_h`` its raw gradient's symmetric part, ``e_t`` the true
    strain, shear counted twice: ``int_K |e_h - e_t|^2`` less ``int_K |e_t|^2``, which is the same for a box and
    its halves, so differences of it are differences of the floor error.

    ``int_K |e_h|^2``: 3 x 3 Gauss (exact).  The cross term ``int_K sym(G_h) : grad u_t``: over :data:`BOX_SUB`
    sub-cells per direction, ``int_cell S d_x u = int_y S(x_mid, y) (u(x_b, y) - u(x_a, y)) dy`` (3-point Gauss
    in y), likewise in y: it needs the displacement only, so a step of the true strain inside the box (an
    inclusion's rim, a band's face) costs no quadrature error beyond the variation of ``S`` across one sub-cell
    (none for ``S`` constant along the derivative's axis); point samples of ``e_t`` would err by the step's size.
    """
    x0, x1, y0, y1 = (np.asarray(v, float) for v in (x0, x1, y0, y1))
    hx, hy = x1 - x0, y1 - y0
    U = {(i, j): np.asarray(field.displacement(np.column_stack([x0 + i * hx, y0 + j * hy])), float)
         for i in (0, 1) for j in (0, 1)}

    def grad_h(r, s):
        """(n, 2, 2) gradient of u_h at reference (r, s): [i, j] = d u_i / d x_j."""
        r, s = np.asarray(r, float)[..., None], np.asarray(s, float)[..., None]
        dx = ((1 - s) * (U[1, 0] - U[0, 0]) + s * (U[1, 1] - U[0, 1])) / hx[:, None]
        dy = ((1 - r) * (U[0, 1] - U[0, 0]) + r * (U[1, 1] - U[1, 0])) / hy[:, None]
        return np.stack([dx, dy], axis=-1)

    def sym(G):
        return 0.5 * (G + np.swapaxes(G, -1, -2))

    energy = np.zeros(x0.size)
    for a in range(3):
        for b in range(3):
            S = sym(grad_h(np.full(x0.size, _G3[a]), np.full(x0.size, _G3[b])))
            energy += _W3[a] * _W3[b] * np.sum(S * S, axis=(1, 2))
    energy *= hx * hy
    m = BOX_SUB
    edges = np.arange(m + 1) / m
    mids = 0.5 * (edges[:-1] + edges[1:])
    gq = ((np.arange(m)[:, None] + _G3[None, :]) / m).ravel()       # composite Gauss along the other axis
    wq = np.tile(_W3, m) / m
    cross = np.zeros(x0.size)
    for q, w in zip(gq, wq):
        # d/dx terms: sub-cells along x at y = y0 + q hy
        ux = [np.asarray(field.displacement(np.column_stack([x0 + e * hx, y0 + q * hy])), float) for e in edges]
        for k in range(m):
            S = sym(grad_h(np.full(x0.size, mids[k]), np.full(x0.size, q)))
            cross += w * hy * np.sum(S[:, :, 0] * (ux[k + 1] - ux[k]), axis=1)
        # d/dy terms: sub-cells along y at x = x0 + q hx
        uy = [np.asarray(field.displacement(np.column_stack([x0 + q * hx, y0 + e * hy])), float) for e in edges]
        for k in range(m):
            S = sym(grad_h(np.full(x0.size, q), np.full(x0.size, mids[k])))
            cross += w * hx * np.sum(S[:, :, 1] * (uy[k + 1] - uy[k]), axis=1)
    return energy - 2.0 * cross


def directional_scores(mesh, field):
    """Row and column scores of a tensor mesh: the sum over a row (column) of the elements' drop of
    :func:`box_energy` when each is halved along depth (laterally) -- what splitting that row (column) alone buys.
    Returns ``(rows (n_x - 1,), cols (n_y - 1,))``."""
    from femreg.mesh import tensor_structure

    xs, ys, cell = tensor_structure(mesh)
    I, J = np.meshgrid(np.arange(xs.size - 1), np.arange(ys.size - 1), indexing="ij")
    x0, x1, y0, y1 = xs[I].ravel(), xs[I + 1].ravel(), ys[J].ravel(), ys[J + 1].ravel()
    xm, ym = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    e0 = box_energy(field, x0, x1, y0, y1)
    gx = e0 - box_energy(field, x0, xm, y0, y1) - box_energy(field, xm, x1, y0, y1)
    gy = e0 - box_energy(field, x0, x1, y0, ym) - box_energy(field, x0, x1, ym, y1)
    return gx.reshape(I.shape).sum(1), gy.reshape(I.shape).sum(0)


def _done(kind, own, step, steps, max_steps, rows):
    """The ``tensor`` mesh stops after ``steps``; the others go on (up to ``max_steps``) until they reach the tensor
    mesh's last floor, or stall (the last two steps together less than 2 % lower)."""
    if kind == "tensor" or step >= max_steps:
        return kind == "tensor" and step >= steps or step >= max_steps
    tensor = [r for r in rows if r["type"] == "tensor" and r["case"] == own[-1]["case"]]
    if step >= steps and (not tensor or own[-1]["e"] <= tensor[-1]["e"]):
        return True
    return step >= 2 and own[-1]["e"] > 0.98 * own[-3]["e"]


def roi_truth(case, field):
    """ROI sample axes ``xg``, ``yg`` (mm), the true fields on them (dict of (nx, ny) arrays, as
    :func:`benchmarks.robustness.truth`) and the ring / band zone (bool (nx, ny))."""
    shape, spacing, origin = case_geometry(case)
    sl = roi_slices(shape, spacing)
    xg = origin[0] + np.arange(sl[0].start, sl[0].stop, sl[0].step) * spacing[0]
    yg = origin[1] + np.arange(sl[1].start, sl[1].stop) * spacing[1]
    X, Y = np.meshgrid(xg, yg, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    u_t, e_t = field.displacement(P), field.strain(P)
    t_roi = {k: v.reshape(X.shape) for k, v in (("ux", u_t[:, 0]), ("uy", u_t[:, 1]), ("exx", e_t[:, 0]),
                                                 ("eyy", e_t[:, 1]), ("exy", e_t[:, 2]))}
    if hasattr(field, "radius_mm"):
        d = np.hypot(X - field.centre[0], Y - field.centre[1]) / field.radius_mm
        zone = (d > 0.8) & (d < 1.2)
    else:
        zone = np.abs(X - field.depth_mm) < field.thickness_mm
    return xg, yg, t_roi, zone


def femreg_row(case, progress=True):
    """The floor of the mesh femreg's defaults refine to on the case's rendered pair (its own base element size
    from the speckle, its data-driven marking, :data:`femreg.refine.DEEP_REFINEMENT`): one row, type
    ``"femreg default"``, regime ``"pixel"``."""
    import warnings

    import femreg
    from benchmarks.robustness import make_data

    data = make_data(case)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin)
    xg, yg, t_roi, zone = roi_truth(case, data.field)
    st = MeshState("rect", res.mesh.p, res.mesh.t, data.field)
    e_rec, e_el, e_zone = _scores(st, xg, yg, t_roi, zone)
    mn = st.min_size()
    row = dict(case=case.name, regime="pixel", type="femreg default", step=0, nodes=st.n_free,
               elements=st.t.shape[1], min_ax=mn[0], min_lat=mn[1], e=100 * e_rec, e_element=100 * e_el,
               e_zone=100 * e_zone)
    if progress:
        print(f"{case.name:20s} femreg default: {row['nodes']} nodes, e {row['e']:.2f} %, zone {row['e_zone']:.2f} %",
              flush=True)
    return row


def run_case(case, steps=5, theta=0.5, free=False, types=MESH_TYPES, progress=True, max_steps=None):
    """Rows (dict) per mesh type x refinement step for one case (module docstring); the tensor mesh refined
    ``steps`` times, the others until they reach its last floor (:func:`_done`, at most ``max_steps``, default
    ``3 steps``)."""
    from skfem import MeshTri1

    from femreg.mesh import roi_mesh, tensor_structure

    max_steps = 3 * steps if max_steps is None else int(max_steps)
    field = case.field()
    shape, spacing, origin = case_geometry(case)
    base = roi_mesh(shape, spacing, origin, element_size=BASE_ELEMENT_MM)
    xs, ys = tensor_structure(base)[:2]
    xg, yg, t_roi, zone = roi_truth(case, field)
    min_size = (0.0, 0.0) if free else (MIN_AXIAL_MM, 2 * spacing[1])
    rows = []
    for kind in types:
        t0 = time.process_time()
        if kind.startswith("tensor"):
            mesh = base
        elif kind == "quadtree":
            qt = QuadTree(xs, ys)
        else:
            tri = MeshTri1.init_tensor(xs, ys)
        own = [r for r in rows if r["type"] == kind]
        for step in range(max_steps + 1):
            if kind.startswith("tensor"):
                st = MeshState("rect", mesh.p, mesh.t, field)
            elif kind == "quadtree":
                st = MeshState("rect", qt.p, qt.t, field, qt.hanging, qt.free)
            else:
                st = MeshState("tri", tri.p, tri.t, field)
            e_rec, e_el, e_zone = _scores(st, xg, yg, t_roi, zone)
            mn = st.min_size()
            rows.append(dict(case=case.name, regime="free" if free else "pixel", type=kind, step=step,
                             nodes=st.n_free, elements=st.t.shape[1], min_ax=mn[0], min_lat=mn[1], e=100 * e_rec,
                             e_element=100 * e_el, e_zone=100 * e_zone))
            if progress:
                r = rows[-1]
                print(f"{case.name:20s} {kind:8s} step {step}: {r['nodes']:6d} nodes {r['elements']:6d} el, "
                      f"min {mn[0]:.3f} x {mn[1]:.3f} mm, e {r['e']:.2f} % (element {r['e_element']:.2f}), "
                      f"zone {r['e_zone']:.2f} %  [{time.process_time() - t0:.1f} s]", flush=True)
            own.append(rows[-1])
            if _done(kind, own, step, steps, max_steps, rows):
                break
            if kind == "tensor-dir":
                mesh = _refine_tensor_dir(mesh, field, theta, spacing, origin, min_size, free)
                if mesh is None:
                    break
                continue
            eta2 = st.eta2()
            x, y = st.p[0, st.t], st.p[1, st.t]
            ext = np.column_stack([x.max(0) - x.min(0), y.max(0) - y.min(0)])
            if kind == "tensor":
                # its row or its column can still be split
                eligible = np.any(0.5 * ext >= np.asarray(min_size) * (1 - 1e-9), axis=1)
            else:
                eligible = np.all(0.5 * ext >= np.asarray(min_size) * (1 - 1e-9), axis=1)
            marked = doerfler(eta2, theta, eligible)
            if not marked.any():
                break
            if kind == "tensor":
                mesh = _refine_tensor(mesh, marked, spacing, origin, min_size, free)
            elif kind == "quadtree":
                qt.refine(np.flatnonzero(marked))
            else:
                tri = tri.refined(np.flatnonzero(marked))
    return rows


def _refine_tensor(mesh, marked, spacing, origin, min_size, free):
    """Split the rows and the columns holding a marked element: femreg's split (pixel-cell boundaries, at least
    2 pixels and ``min_size``), or with ``free`` at the exact midpoints."""
    from skfem import MeshQuad1

    from femreg.mesh import tensor_structure
    from femreg.refine import refine_tensor_mesh

    xs, ys, cell = tensor_structure(mesh)
    rows = np.zeros(xs.size - 1, bool)
    cols = np.zeros(ys.size - 1, bool)
    i, j = np.nonzero(np.isin(cell, np.flatnonzero(marked)))
    rows[i], cols[j] = True, True
    if free:
        nx = np.union1d(xs, 0.5 * (xs[:-1] + xs[1:])[rows])
        ny = np.union1d(ys, 0.5 * (ys[:-1] + ys[1:])[cols])
        return MeshQuad1.init_tensor(nx, ny)
    return refine_tensor_mesh(mesh, rows, cols, spacing, origin, min_size=min_size, levels=1)[0]


def _refine_tensor_dir(mesh, field, theta, spacing, origin, min_size, free):
    """Split the rows / columns chosen by Doerfler marking on :func:`directional_scores` (rows and columns in one
    list, those that may not be split left out); None when none may be split."""
    from femreg.mesh import tensor_structure

    xs, ys, _ = tensor_structure(mesh)
    gr, gc = directional_scores(mesh, field)
    ok = np.concatenate([0.5 * np.diff(xs) >= min_size[0] * (1 - 1e-9), 0.5 * np.diff(ys) >= min_size[1] * (1 - 1e-9)])
    marked = doerfler(np.maximum(np.concatenate([gr, gc]), 0.0), theta, ok)
    if not marked.any():
        return None
    rows, cols = marked[:gr.size], marked[gr.size:]
    if free:
        from skfem import MeshQuad1

        return MeshQuad1.init_tensor(np.union1d(xs, 0.5 * (xs[:-1] + xs[1:])[rows]),
                                     np.union1d(ys, 0.5 * (ys[:-1] + ys[1:])[cols]))
    from femreg.refine import refine_tensor_mesh

    new, sx, sy = refine_tensor_mesh(mesh, rows, cols, spacing, origin, min_size=min_size, levels=1)
    return new if sx + sy else None


def _loglog(x, y, at):
    """``y`` at ``at`` by log-log interpolation along the (increasing) ``x``; NaN outside ``x``'s range."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    a = np.log(float(at))
    if not x[0] - 1e-12 <= a <= x[-1] + 1e-12:
        return float("nan")
    return float(np.exp(np.interp(a, x, y)))


def nodes_to_reach(rows, target):
    """Free nodes at which the floor error (log-log interpolation between steps) first drops to ``target`` %;
    NaN when it never does."""
    n = np.array([r["nodes"] for r in rows], float)
    e = np.array([r["e"] for r in rows], float)
    for k in range(len(e)):
        if e[k] <= target:
            if k == 0:
                return float(n[0])
            a = (np.log(target) - np.log(e[k - 1])) / (np.log(e[k]) - np.log(e[k - 1]))
            return float(np.exp(np.log(n[k - 1]) + a * (np.log(n[k]) - np.log(n[k - 1]))))
    return float("nan")


def table(rows) -> str:
    lines = ["| regime | case | mesh | step | nodes | elements | smallest mm (ax x lat) | floor e % "
             "| element-strain e % | ring / band e % |\n", "|---|---|---|---|---|---|---|---|---|---|\n"]
    for r in rows:
        lines.append(f"| {r['regime']} | {r['case']} | {r['type']} | {r['step']} | {r['nodes']} | {r['elements']} | "
                     f"{r['min_ax']:.2f} x {r['min_lat']:.2f} | {r['e']:.2f} | {r['e_element']:.2f} | "
                     f"{r['e_zone']:.2f} |\n")
    return "".join(lines)


def summary(rows, key="e") -> str:
    """Per regime x case: every type's floor (``key``: ``"e"`` the ROI, ``"e_zone"`` the ring / band zone) at a
    common node count ``N`` (the smallest of the types' last node counts, log-log interpolation), and the nodes
    each type needs to reach the ``tensor`` mesh's last ROI floor."""
    others = [k for k in MESH_TYPES if k != "tensor"]
    what = "ROI" if key == "e" else "ring / band"
    head = "| regime | case | N | " + " | ".join(f"{what} e % at N: {k}" for k in MESH_TYPES)
    fem = {(r["regime"], r["case"]): r for r in rows if r["type"] == "femreg default"}
    if key == "e":
        head += " | tensor's last: nodes / e % | " + " | ".join(f"nodes to reach it: {k}" for k in others)
    if fem:
        head += " | femreg default mesh: nodes / e %"
    lines = [head + " |\n", "|" + "---|" * head.count("|") + "\n"]

    def f(v, fmt):
        return "not reached" if not np.isfinite(v) else format(v, fmt)

    for regime, case in dict.fromkeys((r["regime"], r["case"]) for r in rows):
        by = {k: [r for r in rows if r["case"] == case and r["type"] == k and r["regime"] == regime]
              for k in MESH_TYPES}
        if not all(by.values()):
            continue
        n = min(v[-1]["nodes"] for v in by.values())
        at = [_loglog([r["nodes"] for r in by[k]], [r[key] for r in by[k]], n) for k in MESH_TYPES]
        line = f"| {regime} | {case} | {n} | " + " | ".join(f(v, ".2f") for v in at)
        if key == "e":
            last = by["tensor"][-1]
            need = [nodes_to_reach(by[k], last["e"]) for k in others]
            line += f" | {last['nodes']} / {last['e']:.2f} | " + " | ".join(f(v, ".0f") for v in need)
        if fem:
            r = fem.get((regime, case))
            line += " | n/a" if r is None else f" | {r['nodes']} / {r[key]:.2f}"
        lines.append(line + " |\n")
    return "".join(lines)


def last_steps(rows) -> str:
    """:func:`table` of each regime x case x type's first and last step."""
    keep = []
    for i, r in enumerate(rows):
        nxt = rows[i + 1] if i + 1 < len(rows) else None
        if r["step"] == 0 or nxt is None or nxt["type"] != r["type"] or nxt["case"] != r["case"]:
            keep.append(r)
    return table(keep)


def plot(rows, path):
    """Floor error against free nodes (log-log), one panel per case, one row per regime."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    cases = list(dict.fromkeys(r["case"] for r in rows))
    regimes = list(dict.fromkeys(r["regime"] for r in rows))
    fig, axes = plt.subplots(len(regimes), len(cases), figsize=(2.1 * len(cases), 2.0 * len(regimes) + 0.3),
                             constrained_layout=True, squeeze=False)
    style = {"tensor": ("o-", "C0"), "tensor-dir": ("o--", "C3"), "quadtree": ("s-", "C1"), "tri": ("^-", "C2")}
    for i, regime in enumerate(regimes):
        for ax, case in zip(axes[i], cases):
            for k in MESH_TYPES:
                rr = [r for r in rows if r["case"] == case and r["type"] == k and r["regime"] == regime]
                if rr:
                    ax.loglog([r["nodes"] for r in rr], [r["e"] for r in rr], style[k][0], color=style[k][1],
                              ms=2.5, lw=0.9, label=k)
            fr = [r for r in rows if r["case"] == case and r["type"] == "femreg default" and r["regime"] == regime]
            if fr:
                ax.loglog([r["nodes"] for r in fr], [r["e"] for r in fr], "k*", ms=5, label="femreg default")
            ax.set_title(f"{case}\n{regime}", fontsize=6)
            ax.tick_params(labelsize=5, which="both")
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:g}"[0] in "2357" else ""))
            ax.grid(True, which="both", lw=0.3, alpha=0.5)
            if i == len(regimes) - 1:
                ax.set_xlabel("free nodes", fontsize=6)
        axes[i, 0].set_ylabel("floor strain error %", fontsize=6)
    axes[0, 0].legend(fontsize=5)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="")
    ap.add_argument("--types", default=",".join(MESH_TYPES))
    ap.add_argument("--steps", type=int, default=5, help="refinement steps of the tensor mesh")
    ap.add_argument("--theta", type=float, default=0.5, help="Doerfler fraction")
    ap.add_argument("--regimes", default="pixel,free",
                    help="pixel: femreg's size limits; free: midpoint splits, no pixel grid, no size limit")
    ap.add_argument("--out", default="out/mesh_types")
    ap.add_argument("--plot", default="")
    ap.add_argument("--from-json", default="", help="tables and plot from a previous run's results.json")
    ap.add_argument("--femreg", action="store_true",
                    help="also the floor of the mesh femreg's defaults refine to on each case's rendered pair")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    words = [w for w in a.cases.split(",") if w]
    types = [t for t in a.types.split(",") if t]
    rows = json.loads(Path(a.from_json).read_text()) if a.from_json else []
    for regime in [] if a.from_json else [w for w in a.regimes.split(",") if w]:
        if regime not in ("pixel", "free"):
            raise SystemExit(f"unknown regime {regime!r} (pixel, free)")
        for case in CASES:
            if not words or any(w in case.name for w in words):
                rows += run_case(case, a.steps, a.theta, regime == "free", types)
                if a.femreg and regime == "pixel":
                    rows.append(femreg_row(case))
    md = (summary(rows) + "\n" + summary(rows, "e_zone") + "\n" + last_steps(rows) + "\n## Every step\n\n"
          + table(rows))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text(md)
    (out / "results.json").write_text(json.dumps(rows, indent=0))
    if a.plot:
        plot(rows, a.plot)
    print("\n" + md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
