"""Adaptive refinement of convex / sector frames (femreg.geometry + femreg.refine): the (range, angle) lattice
the physical mesh carries, the jumps of A[u] across the physical edges, the split and transfer there, and a
refined convex registration of a stiff inclusion."""
import pickle

import numpy as np
import pytest

import femreg
from femreg.fields import element_strains
from femreg.geometry import physical_mesh
from femreg.mesh import roi_mesh
from femreg.metrics import field_errors
from femreg.refine import (DEFAULT, _momentum, default_refine, edge_jumps, logical_grid, refine_tensor_mesh, transfer,
                           with_logical_grid)
from forward import fields as F
from forward.beam import make_beam_pair


def _fan(geo=femreg.Convex(40.0, 0.6), shape=(400, 40), dr=0.05, r0=3.0):
    rho_c = geo.radius_mm + r0 + 0.5 * (shape[0] - 1) * dr
    ds = rho_c * geo.pitch_rad
    m_s = roi_mesh(shape, (dr, ds), (r0, -0.5 * (shape[1] - 1) * ds), element_size=(2.0, 2.0))

    def to_logical(p):
        r, th = geo.to_beam(p[:, 0], p[:, 1])
        return np.stack([r, rho_c * th])
    mesh = with_logical_grid(m_s, lambda q: np.asarray(q)[1] / rho_c, lambda m: physical_mesh(m, geo, rho_c),
                             to_logical)
    return mesh, m_s, (dr, ds), (r0, -0.5 * (shape[1] - 1) * ds)


def test_jumps_across_the_physical_edges():
    # |[[A]] n| and |t . [[A]] n| with n the normal of each physical edge (from its two nodes), against the
    # logical grid's: the ray edges and the chords between rays
    mesh, m_s, _, _ = _fan()
    rng = np.random.default_rng(0)
    u = 1e-2 * rng.standard_normal(2 * mesh.p.shape[1])
    ja, jl, ta, tl = edge_jumps(mesh, u, tangential=True)
    Axx, Ayy, Axy = _momentum(element_strains(mesh.p, mesh.t, u))
    from femreg.mesh import tensor_structure, tensor_node_grid
    xs, ys, cell = tensor_structure(m_s)
    node = tensor_node_grid(m_s, xs, ys)

    def explicit(c0, c1, a, b):
        d = mesh.p[:, b] - mesh.p[:, a]
        n = np.array([d[1], -d[0]]) / np.hypot(*d)
        dA = np.array([[Axx[c1] - Axx[c0], Axy[c1] - Axy[c0]], [Axy[c1] - Axy[c0], Ayy[c1] - Ayy[c0]]])
        J = dA @ n
        return np.hypot(*J), abs(J[1] * n[0] - J[0] * n[1])
    for i, k in [(0, 0), (3, 7), (cell.shape[0] - 2, cell.shape[1] - 1)]:     # between rows i, i + 1 in column k
        want = explicit(cell[i, k], cell[i + 1, k], node[i + 1, k], node[i + 1, k + 1])
        assert np.allclose((ja[i, k], ta[i, k]), want, rtol=1e-10, atol=1e-14)
    for i, k in [(0, 0), (5, 3), (cell.shape[0] - 1, cell.shape[1] - 2)]:     # between columns k, k + 1 in row i
        want = explicit(cell[i, k], cell[i, k + 1], node[i, k + 1], node[i + 1, k + 1])
        assert np.allclose((jl[i, k], tl[i, k]), want, rtol=1e-10, atol=1e-14)
    # a uniform physical strain: no jump on the fan (its A is the same in every element)
    comp = F.compression(0.02).displacement(mesh.p.T)
    ja, jl = edge_jumps(mesh, comp.ravel())
    assert max(ja.max(), jl.max()) < 1e-12


def test_split_and_transfer_on_the_lattice():
    mesh, m_s, sp, org = _fan()
    rows = np.zeros(len(np.unique(m_s.p[0])) - 1, bool)
    cols = np.zeros(len(np.unique(m_s.p[1])) - 1, bool)
    rows[4], cols[2] = True, True
    new, sx, sy = refine_tensor_mesh(mesh, rows, cols, sp, org)
    assert (sx, sy) == (1, 1) and logical_grid(new) is not None
    assert new.t.shape[1] == (rows.size + 1) * (cols.size + 1)
    # the refined physical mesh is the refined lattice mapped: every node on its ray at its range
    lg = logical_grid(new)
    assert np.allclose(lg.to_logical(new.p.T), lg.mesh.p, atol=1e-9)
    # nodal values carried bilinearly in (r, s): the coarse nodes keep theirs, a field linear in (r, s) is exact
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = 0.01 * m_s.p[0] - 0.002 * m_s.p[1], 0.003 * m_s.p[1]
    v = transfer(u, mesh, new)
    assert np.allclose(v[0::2], 0.01 * lg.mesh.p[0] - 0.002 * lg.mesh.p[1], atol=1e-12)
    assert np.allclose(v[1::2], 0.003 * lg.mesh.p[1], atol=1e-12)


def test_convex_inclusion_refines_and_the_default_stays_off():
    geo = femreg.Convex(50.0, 0.6)
    pair = make_beam_pair(F.Inclusion("stiff", "plane-strain", 0.01), geo, depth_mm=30.0, n_rays=40, seed=3,
                          top_mm=8.0)
    kw = dict(spacing=pair.spacing, origin=pair.origin, geometry=geo)
    default = femreg.register(pair.ref, pair.mov, **kw)
    off = femreg.register(pair.ref, pair.mov, refine=None, **kw)
    ref = femreg.register(pair.ref, pair.mov, refine="auto", **kw)
    # the default of a convex / sector frame is off (benchmarks/convex_refine.py: uniform compression of sector
    # frames 0.8-1.6 points worse refined, convex ones at 0.3 deg up to 0.9; up to 2.3x the CPU time)
    assert default_refine(DEFAULT, strategy="auto", geometry=geo) is None
    assert getattr(default, "refinement", None) is None and np.array_equal(default.u, off.u)
    assert ref.success and isinstance(ref, femreg.geometry.BeamResult)
    rec = ref.refinement
    assert len(rec.passes) >= 1 and sum(p["rows"] + p["columns"] for p in rec.passes) > 0
    assert ref.mesh.t.shape[1] > off.mesh.t.shape[1] and logical_grid(ref.mesh) is not None
    back = pickle.loads(pickle.dumps(ref.mesh))          # the lattice the mesh carries pickles with it
    assert np.array_equal(logical_grid(back).mesh.p, logical_grid(ref.mesh).mesh.p)
    # the physical solve on the refined mesh keeps the unrefined mesh's weight of eq:objf
    assert ref.alpha_effective == pytest.approx(off.alpha_effective, rel=1e-9) and ref.alpha == off.alpha
    e_off = field_errors(off, pair.true_displacement, pair.true_strain)["e"]
    e_ref = field_errors(ref, pair.true_displacement, pair.true_strain)["e"]
    # measured 16.47 -> 15.72 % (seeds 4, 5: 16.54 -> 15.92, 16.38 -> 15.63 %): the refined error at least
    # 0.3 points below the unrefined one
    assert e_ref < e_off - 0.003, (e_off, e_ref)
    # the unrefined inclusion blends in the projection (measured weight 0.32-0.38, seeds 3-5); a refined result
    # keeps the nodal average (its elements fit a uniform fan's noise past the feature test)
    assert off.recovery_weight > 0.15 and ref.recovery_weight == 0.0
    g = ref.on_grid()
    assert g["exx"].shape == pair.ref.shape and np.isfinite(g["exx"]).mean() > 0.6
