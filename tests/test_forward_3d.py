"""3D forward model: symmetry about the imaging plane, quarter vs full model, convergence under refinement.

The default-suite versions use coarse meshes (seconds); the study at production mesh sizes is marked slow
(benchmarks/bench_forward.py prints the same study with timings and memory).
"""
import numpy as np
import pytest

import forward

#: points of the imaging plane away from the inclusion interface (r = 7.5 mm around (30, 0)) and the patch edge
PTS = np.array([[30.0, 0.0], [30.0, 3.0], [26.0, -2.0], [50.0, 10.0], [15.0, 15.0], [60.0, -5.0], [45.0, 0.0],
                [10.0, 0.0], [70.0, 20.0]])


@pytest.fixture(scope="module")
def full_and_quarter():
    kw = dict(mesh_size_mm=6.0, coarse_size_mm=24.0)
    return (forward.solve_elasticity("3d", symmetry="full", **kw),
            forward.solve_elasticity("3d", symmetry="quarter", **kw))


def test_symmetric_about_imaging_plane(full_and_quarter):
    """Full model (its mesh is not symmetric): u_x, u_y even and u_z odd in z; u_y odd in y.  The deviation is
    measured relative to the largest displacement magnitude; with 6 mm / 24 mm elements it is discretisation error
    of a few per cent at most."""
    full, _ = full_and_quarter
    rng = np.random.default_rng(5)
    p = rng.uniform([2, -40, 1], [100, 40, 40], (200, 3))
    u = full.displacement_3d(p)
    um = full.displacement_3d(p * [1, 1, -1])
    scale = np.linalg.norm(u, axis=1).max()
    dev = np.abs(u - um * [1, 1, -1]).max(axis=0) / scale
    assert np.all(dev < 0.03), f"mirror deviation about z=0 per component (rel. to max |u|): {dev}"
    uy = full.displacement_3d(p * [1, -1, 1])
    devy = np.abs(u - uy * [1, -1, 1]).max(axis=0) / scale
    assert np.all(devy < 0.03), f"mirror deviation about y=0: {devy}"


def test_quarter_model_matches_full(full_and_quarter):
    full, quarter = full_and_quarter
    assert quarter.info["n_dofs"] < 0.5 * full.info["n_dofs"], (quarter.info["n_dofs"], full.info["n_dofs"])
    rq, rf = quarter.info["reaction_force"], full.info["reaction_force"]
    assert abs(rq - rf) / rf < 0.02, f"reaction quarter {rq:.2f} N vs full {rf:.2f} N"
    eq, ef = quarter.strain(PTS), full.strain(PTS)
    d = np.abs(eq - ef).max() / np.abs(ef[:, 0]).max()
    assert d < 0.1, f"imaging-plane strain quarter vs full (coarse 6 mm meshes): max rel. diff {d:.3f}"
    # reconstructed quarter model: u_y odd / e_xy odd in y by construction
    e1, e2 = quarter.strain(np.array([[40.0, 12.0]])), quarter.strain(np.array([[40.0, -12.0]]))
    assert np.allclose(e1 * [1, 1, -1], e2)


def _study(levels):
    R, E, n = [], [], []
    for h, hc in levels:
        s = forward.solve_elasticity("3d", mesh_size_mm=h, coarse_size_mm=hc)
        R.append(s.info["reaction_force"])
        E.append(s.strain(PTS)[:, 0])
        n.append(s.info["n_dofs"])
    return np.array(R), np.array(E), n


def _assert_converging(levels, tol_last):
    R, E, n = _study(levels)
    # displacement-driven problem: FE energy (= R c / 2) decreases as the space grows (upper bound)
    assert np.all(np.diff(R) < 0), f"reaction force not decreasing under refinement: {R} (DOFs {n})"
    assert abs(R[-1] - R[-2]) < abs(R[-2] - R[-3]) or abs(R[-1] - R[-2]) / R[-1] < 0.005, f"reaction {R}"
    scale = np.abs(E[-1]).max()
    d1 = np.abs(E[1] - E[0]).max() / scale
    d2 = np.abs(E[2] - E[1]).max() / scale
    assert d2 < d1 and d2 < tol_last, (f"imaging-plane e_xx changes {d1:.4f} -> {d2:.4f} (DOFs {n}); "
                                       f"reaction {R}")
    return R, d1, d2


def test_3d_converges_coarse():
    _assert_converging([(6.0, 24.0), (4.0, 16.0), (3.0, 12.0)], tol_last=0.03)


@pytest.mark.slow
def test_3d_converges_production_meshes():
    R, d1, d2 = _assert_converging([(2.0, 16.0), (1.5, 16.0), (1.0, 16.0)], tol_last=0.02)
    print(f"reaction {R}, e_xx change {d1:.4f} -> {d2:.4f}")
