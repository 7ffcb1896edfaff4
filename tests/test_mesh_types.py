"""The mesh-type benchmark's helpers: the quadtree's constrained hanging-node interpolant (continuous across
coarse-fine edges, exact for affine fields, 2:1 balanced) and the P1 triangle strain.  No image, no FE solve."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import mesh_types as M  # noqa: E402


class _Field:
    """u = A x + b (affine) plus ``curv`` times a smooth non-polynomial part; strain of the affine part only."""

    A = np.array([[0.01, -0.02], [0.03, 0.005]])

    def __init__(self, curv=0.0):
        self.curv = curv

    def displacement(self, P):
        P = np.asarray(P, float)
        u = P @ self.A.T + np.array([1.0, -0.5])
        return u + self.curv * np.column_stack([np.sin(P[:, 0]) * P[:, 1] ** 2, np.cos(P[:, 1] * P[:, 0])])

    def strain(self, P):
        e = 0.5 * (self.A + self.A.T)
        return np.tile([e[0, 0], e[1, 1], e[0, 1]], (len(P), 1))


def _corner_tree():
    """4 x 3 base cells (one of them 2 mm wide); three times, the smallest leaf at the edge x = 1 (bottom) split:
    its children touch the coarse base cell beyond that edge, which the 2:1 balance must then split."""
    qt = M.QuadTree([0.0, 1.0, 2.0, 4.0, 5.0], [0.0, 1.0, 2.0, 3.0])
    for _ in range(3):
        c = qt.p[:, qt.t]
        at = np.flatnonzero((c[0].max(0) == 1.0) & (c[1].min(0) == 0.0))
        qt.refine(at[np.argmin(np.ptp(c[0][:, at], axis=0))])
    return qt


def test_quadtree_balanced_with_hanging_nodes():
    qt = _corner_tree()
    # the balance split neighbours: more than the 12 + 3 x 3 leaves of the three splits alone
    assert qt.t.shape[1] > 21
    assert len(qt.hanging) > 0 and np.count_nonzero(~qt.free) == len(qt.hanging)
    # 2:1: no leaf edge carries a node at its quarter points
    keys = set(qt.keys.tolist())
    B = qt.boxes
    for X0, X1, Y0, Y1 in B:
        for q in (1, 3):
            for x, y in (((X0 * (4 - q) + X1 * q) // 4, Y0), ((X0 * (4 - q) + X1 * q) // 4, Y1),
                         (X0, (Y0 * (4 - q) + Y1 * q) // 4), (X1, (Y0 * (4 - q) + Y1 * q) // 4)):
                assert int(qt._key(x, y)) not in keys


def test_hanging_interpolant_exact_for_affine_and_continuous():
    qt = _corner_tree()
    aff = M.MeshState("rect", qt.p, qt.t, _Field(), qt.hanging, qt.free)
    assert np.abs(aff.u - _Field().displacement(qt.p.T)).max() < 1e-12
    assert np.abs(aff.s - _Field().strain(qt.p.T)).max() < 1e-12          # recovered strain exact too
    assert aff.eta2().max() < 1e-25
    # a curved field: on every leaf edge, the values from both sides agree (no gap at a hanging node)
    st = M.MeshState("rect", qt.p, qt.t, _Field(curv=0.2), qt.hanging, qt.free)
    p, t = st.p, st.t
    lo, hi = p[:, t].min(1), p[:, t].max(1)          # (2, n_el) boxes
    s = np.linspace(0.0, 1.0, 7)
    gap, checked = 0.0, 0
    for k in range(t.shape[1]):
        for X, Y in ((lo[0, k] + 0 * s, lo[1, k] + s * (hi[1, k] - lo[1, k])),
                     (hi[0, k] + 0 * s, lo[1, k] + s * (hi[1, k] - lo[1, k])),
                     (lo[0, k] + s * (hi[0, k] - lo[0, k]), lo[1, k] + 0 * s),
                     (lo[0, k] + s * (hi[0, k] - lo[0, k]), hi[1, k] + 0 * s)):
            mine = M._rect_bilinear(p, t, st.u, np.full(s.size, k), X, Y)
            for j in range(t.shape[1]):
                inside = ((X >= lo[0, j] - 1e-12) & (X <= hi[0, j] + 1e-12) & (Y >= lo[1, j] - 1e-12)
                          & (Y <= hi[1, j] + 1e-12))
                if j != k and inside.any():
                    other = M._rect_bilinear(p, t, st.u, np.full(inside.sum(), j), X[inside], Y[inside])
                    gap = max(gap, float(np.abs(other - mine[inside]).max()))
                    checked += 1
    assert checked > 50 and gap < 1e-12
    # without the constraint the hanging nodes' exact values open a gap of the curvature's size
    raw = np.asarray(_Field(curv=0.2).displacement(p.T))
    h, a, b = qt.hanging.T
    assert np.abs(raw[h] - 0.5 * (raw[a] + raw[b])).max() > 1e-3


def test_triangle_strain_and_doerfler():
    from skfem import MeshTri1

    m = MeshTri1.init_tensor([0.0, 1.0, 2.5], [0.0, 0.5, 2.0]).refined(np.array([0, 3]))
    e = M.tri_strains(m.p, m.t, _Field().displacement(m.p.T))
    assert np.abs(e - _Field().strain(m.p.T[:1])).max() < 1e-14
    eta = np.array([4.0, 1.0, 3.0, 2.0])
    assert M.doerfler(eta, 0.5, np.ones(4, bool)).tolist() == [True, False, True, False]   # 7 >= 5, 4 < 5
    assert M.doerfler(eta, 0.5, np.array([False, True, True, True])).tolist() == [False, False, True, False]  # 3 of 6


class _Layer:
    """A smooth shear layer at depth 2 mm: u_y = 0.05 tanh((x - 2) / 0.3), depth only."""

    def displacement(self, P):
        P = np.asarray(P, float)
        return np.column_stack([0 * P[:, 0], 0.05 * np.tanh((P[:, 0] - 2.0) / 0.3)])

    def strain(self, P):
        P = np.asarray(P, float)
        g = 0.05 / 0.3 / np.cosh((P[:, 0] - 2.0) / 0.3) ** 2
        return np.column_stack([0 * g, 0 * g, 0.5 * g])


def test_directional_scores_pick_rows_for_a_layer():
    from skfem import MeshQuad1

    mesh = MeshQuad1.init_tensor(np.linspace(0.0, 4.0, 5), np.linspace(-2.0, 2.0, 5))
    rows, cols = M.directional_scores(mesh, _Layer())
    assert np.abs(cols).max() < 1e-15                       # nothing varies laterally
    assert rows.min() >= 0 and np.argmax(rows) in (1, 2)    # the rows at the layer (x 1-3 mm) gain most
    assert rows[[1, 2]].min() > 10 * rows[[0, 3]].max()


def test_box_energy_affine_and_step():
    # affine u: e_h = e_t, so |e_h|^2 - 2 e_h : e_t = -|e_t|^2 (shear twice) times the area
    f = _Field()
    e = f.strain(np.zeros((1, 2)))[0]
    x0, x1, y0, y1 = np.array([0.0, 1.0]), np.array([0.5, 3.0]), np.array([-1.0, 2.0]), np.array([0.0, 2.2])
    want = -(e[0] ** 2 + e[1] ** 2 + 2 * e[2] ** 2) * (x1 - x0) * (y1 - y0)
    assert np.allclose(M.box_energy(f, x0, x1, y0, y1), want, rtol=1e-12, atol=0)
    # a band's step (e_xy = g inside |x - 15| < 0.5): the element's e_xy is the mean of the true one over its
    # depth, so halving [14.887, 15.58] x [0, 0.7] takes off 2 * 0.7 * g^2 (sum over cells of h mean^2 / g^2):
    # children [14.887, 15.2335] (all band) and [15.2335, 15.58] (0.2665 mm of band), parent 0.613 mm of band
    from forward.fields import ShearBand

    band = ShearBand(15.0, 1.0, 0.15, 0.01)
    a, b, m = 14.887, 15.58, 0.5 * (14.887 + 15.58)
    def energy(lo, hi):
        return M.box_energy(band, np.array([lo]), np.array([hi]), np.array([0.0]), np.array([0.7]))[0]

    gain = energy(a, b) - energy(a, m) - energy(m, b)
    g = band.peak_exy
    exact = 0.7 * 2 * g ** 2 * (-(0.613 ** 2) / 0.693 + (m - a) + (15.5 - m) ** 2 / (b - m))
    assert exact > 0 and abs(gain - exact) < 1e-6 * exact
