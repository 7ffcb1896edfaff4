"""forward.elasticity / forward.geometry: API, exactness, point evaluation, I/O, cache, bad input."""
import numpy as np
import pytest

import forward
from forward import geometry

COARSE2D = dict(mesh_size_mm=3.0, coarse_size_mm=20.0)


@pytest.fixture(scope="module")
def hi_strain():
    return forward.solve_elasticity("plane-strain", **COARSE2D)


def test_geometry_groups_and_gmsh_finalized():
    import gmsh

    m = geometry.mesh_2d(mesh_size_mm=1.5, coarse_size_mm=20.0)
    assert not gmsh.isInitialized(), "gmsh left initialised"
    assert set(m.subdomains) == {"background", "inclusion"}
    assert {"bottom", "patch", "top_free", "sides"} <= set(m.boundaries)
    patch = m.p[:, m.facets[:, m.boundaries["patch"]]]
    assert np.allclose(patch[0], 0.0) and np.isclose(patch[1].min(), -25) and np.isclose(patch[1].max(), 25)
    # inclusion area ~ pi r^2 (inscribed polygon with ~31 sides of 1.5 mm: deficit ~0.7 %)
    tri = m.t[:, m.subdomains["inclusion"]]
    a, b, c = (m.p[:, tri[i]] for i in range(3))
    area = 0.5 * np.abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])).sum()
    assert abs(area - np.pi * 7.5 ** 2) / (np.pi * 7.5 ** 2) < 0.02, f"inclusion area {area:.2f}"
    m3 = geometry.mesh_3d(mesh_size_mm=6.0, coarse_size_mm=30.0)
    assert not gmsh.isInitialized()
    assert {"bottom", "patch", "top_free", "sides", "sym_y", "sym_z"} <= set(m3.boundaries)
    pf = m3.p[:, m3.facets[:, m3.boundaries["patch"]]]
    assert np.allclose(pf[0], 0) and np.isclose(pf[1].max(), 25) and np.isclose(pf[2].max(), 25)
    # whole-face patch
    m4 = geometry.mesh_2d(patch_mm=None, mesh_size_mm=5.0, coarse_size_mm=20.0)
    assert "top_free" not in m4.boundaries


def test_geometry_off_main_thread():
    import threading

    out = {}
    th = threading.Thread(target=lambda: out.setdefault("m", geometry.mesh_2d(mesh_size_mm=5.0, coarse_size_mm=20)))
    th.start()
    th.join()
    assert out["m"].t.shape[1] > 100


@pytest.mark.parametrize("model", ["plane-strain", "plane-stress", "3d"])
def test_uniform_compression_exact(model):
    """Homogeneous block, whole top face pushed down with slip, bottom sliding: uniaxial stress, exactly
    representable by P2, so e_xx = -c/B and e_yy = nu e_xx-ratio from the closed form everywhere."""
    B, c, nu = 160.0, 1.0, 0.495
    kw = dict(mesh_size_mm=8.0, coarse_size_mm=30.0) if model == "3d" else dict(mesh_size_mm=6.0, coarse_size_mm=25.)
    sol = forward.solve_elasticity(model, inclusion_modulus=10.0, background_modulus=10.0, poisson=nu,
                                   patch_mm=None, compression_mm=c, bottom="slip", **kw)
    pts = np.random.default_rng(1).uniform([0, -80], [160, 80], (300, 2))
    e = sol.strain(pts)
    exx = -c / B
    ratio = nu / (1 - nu) if model == "plane-strain" else nu  # -e_yy / e_xx
    err = np.abs(e - np.array([exx, -ratio * exx, 0.0])).max()
    assert err < 1e-10, f"{model}: max strain error {err:.2e}"
    u = sol.displacement(pts)
    uex = np.c_[c * (1 - pts[:, 0] / B), 0 * pts[:, 1]]
    assert np.abs(u[:, 0] - uex[:, 0]).max() < 1e-10
    # reaction force = sigma * area (N/mm in 2D)
    E_eff = 10.0 / (1 - nu ** 2) if model == "plane-strain" else 10.0
    area = B * B if model == "3d" else B
    assert np.isclose(sol.info["reaction_force"], E_eff * c / B * area, rtol=1e-8), sol.info["reaction_force"]


def test_hi_plane_strain_physics(hi_strain):
    s = hi_strain
    assert s.info["n_dofs"] > 0 and s.info["solve_time_s"] >= 0
    centre = s.strain(np.array([[30.0, 0.0]]))[0]
    side = s.strain(np.array([[30.0, 15.0]]))[0]
    assert centre[0] < 0 and side[0] < centre[0], f"hard inclusion strains less: centre {centre}, side {side}"
    # nearly incompressible plane strain: e_xx + e_yy ~ (1-2nu)/(1-nu) * ... small
    assert abs(centre[0] + centre[1]) < 0.05 * abs(centre[0])
    # lateral symmetry of the full 2D slice: u_x even, u_y odd in y (up to mesh asymmetry)
    p = np.array([[20.0, 10.0], [20.0, -10.0]])
    u = s.displacement(p)
    assert abs(u[0, 0] - u[1, 0]) < 1e-2 * abs(u[0, 0]) and abs(u[0, 1] + u[1, 1]) < 2e-2 * abs(u[0, 1])
    top = s.displacement(np.array([[0.0, 0.0], [0.0, 20.0]]))
    assert np.allclose(top[:, 0], 1.0), f"patch displacement {top[:, 0]}"
    assert np.allclose(s.displacement(np.array([[160.0, 30.0]])), 0.0)


def test_point_evaluation_matches_skfem(hi_strain):
    """The KD-tree + affine-inverse evaluation agrees with scikit-fem's own probes."""
    from skfem import Basis, ElementTriP2, ElementVector

    s = hi_strain
    pts = np.random.default_rng(2).uniform([0, -80], [160, 80], (200, 2))
    ib = Basis(s.mesh, ElementVector(ElementTriP2()))
    ux = ib.split_bases()[0].probes(pts.T) @ s.u[ib.split_indices()[0]]
    uy = ib.split_bases()[1].probes(pts.T) @ s.u[ib.split_indices()[1]]
    u = s.displacement(pts)
    assert np.abs(u - np.c_[ux, uy]).max() < 1e-12, np.abs(u - np.c_[ux, uy]).max()
    # strain vs finite differences of the displacement (interior points away from interfaces)
    h = 1e-5
    p = np.array([[50.0, 30.0], [100.0, -40.0]])
    g = s.displacement_gradient(p)
    fd = np.stack([(s.displacement(p + [h, 0]) - s.displacement(p - [h, 0])) / (2 * h),
                   (s.displacement(p + [0, h]) - s.displacement(p - [0, h])) / (2 * h)], axis=2)
    assert np.abs(g - fd).max() < 1e-6, np.abs(g - fd).max()


def test_outside_points(hi_strain):
    s = hi_strain
    pts = np.array([[10.0, 0.0], [-1.0, 0.0], [10.0, 81.0], [np.nan, 0.0], [161.0, 0.0]])
    e = s.strain(pts)
    assert np.all(np.isfinite(e[0])) and np.all(np.isnan(e[1:])), e
    assert np.all(np.isnan(s.displacement(pts)[1:]))
    with pytest.raises(ValueError, match="points"):
        s.strain(pts, outside="raise")
    with pytest.raises(ValueError, match="points"):
        s.displacement(np.zeros((3, 3)))
    assert list(s.region(np.array([[30.0, 0.0], [60.0, 0.0], [-5.0, 0.0]]))) == [1, 0, -1]


def test_save_load_roundtrip(hi_strain, tmp_path):
    s = hi_strain
    path = s.save(tmp_path / "sol.npz")
    s2 = forward.load_solution(path)
    pts = np.random.default_rng(3).uniform([0, -60], [100, 60], (500, 2))
    assert np.array_equal(s.strain(pts), s2.strain(pts))
    assert s2.params == s.params and s2.model == s.model
    import meshio

    v = s.save(tmp_path / "sol.vtu")
    m = meshio.read(v)
    assert m.point_data["displacement"].shape == (s.mesh.p.shape[1], 3)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        forward.load_solution(tmp_path / "bad.npz")


def test_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FEMREG_CACHE", str(tmp_path))
    from forward.sequences import sequence_cache_dir

    # one cache folder for the simulator: forward solutions and sequences both live under $FEMREG_CACHE
    assert forward.cache_dir() == tmp_path and sequence_cache_dir() == tmp_path / "sequences"
    a = forward.cached_solve("plane-stress", **COARSE2D)
    files = list((tmp_path / "forward").glob("*.npz"))
    assert len(files) == 1
    b = forward.solve_elasticity("plane-stress", cache=True, **COARSE2D)
    assert b.info.get("from_cache") == str(files[0])
    assert np.array_equal(a.u, b.u)
    c = forward.cached_solve("plane-stress", inclusion_modulus=20.0, **COARSE2D)
    assert len(list((tmp_path / "forward").glob("*.npz"))) == 2 and not np.array_equal(a.u, c.u)
    files[0].write_bytes(b"corrupt")   # corrupt entry is recomputed, not an error
    d = forward.cached_solve("plane-stress", **COARSE2D)
    assert np.allclose(d.u, a.u)


@pytest.mark.parametrize("kw, name", [
    (dict(inclusion_modulus=0.0), "inclusion_modulus"),
    (dict(background_modulus=-1.0), "background_modulus"),
    (dict(poisson=0.5), "poisson"),
    (dict(poisson=0.7), "poisson"),
    (dict(inclusion_depth_mm=5.0), "inclusion_depth_mm"),
    (dict(inclusion_depth_mm=200.0), "inclusion_depth_mm"),
    (dict(inclusion_diameter_mm=-3.0), "inclusion_diameter_mm"),
    (dict(block_mm=0.0), "block_mm"),
    (dict(patch_mm=200.0), "patch_mm"),
    (dict(compression_mm=np.nan), "compression_mm"),
    (dict(mesh_size_mm=0.0), "mesh_size_mm"),
    (dict(bottom="glued"), "bottom"),
])
def test_bad_parameters(kw, name):
    with pytest.raises(ValueError, match=name):
        forward.solve_elasticity("plane-strain", **kw)


def test_bad_model_and_symmetry():
    with pytest.raises(ValueError, match="model"):
        forward.solve_elasticity("axisymmetric")
    with pytest.raises(ValueError, match="symmetry"):
        forward.solve_elasticity("3d", symmetry="eighth")
    with pytest.raises(ValueError, match="unknown parameter"):
        forward.cached_solve("3d", modulus=3)


def test_cli_forward(tmp_path, capsys):
    from femreg.cli import main

    out = tmp_path / "ps.npz"
    assert main(["forward", "plane-stress", "--mesh-size-mm", "5", "--coarse-size-mm", "20", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "DOFs" in text and "peak memory" in text
    sol = forward.load_solution(out)
    assert sol.model == "plane-stress" and sol.params["mesh_size_mm"] == 5.0
    assert main(["forward", "plane-strain", "--poisson", "0.5", "-o", str(tmp_path / "x.npz")]) == 2
    assert "poisson" in capsys.readouterr().err


def test_gmsh_session_of_caller_is_kept():
    import gmsh

    gmsh.initialize()
    try:
        gmsh.model.add("callers_model")
        m = geometry.mesh_2d(mesh_size_mm=5.0, coarse_size_mm=20.0)
        assert m.t.shape[1] > 100
        assert gmsh.isInitialized() and "callers_model" in gmsh.model.list()
    finally:
        gmsh.finalize()


def test_demo_01_forward_quick(tmp_path):
    """The demo runs (coarse meshes) and writes its figures; its strain ratio is > 1 for the hard inclusion."""
    import subprocess
    import sys
    from pathlib import Path

    demo = Path(__file__).resolve().parents[1] / "demos" / "01_forward.py"
    r = subprocess.run([sys.executable, str(demo), "--quick"], cwd=tmp_path, capture_output=True, text=True,
                       env={**__import__("os").environ, "MPLBACKEND": "Agg"}, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "out" / "01_forward"
    assert (out / "strains_hi.png").stat().st_size > 10000
    rows = [ln.split() for ln in r.stdout.splitlines() if ln.split() and ln.split()[0] in forward.MODELS]
    assert len(rows) == 3, r.stdout
    sr = {row[0]: float(row[-1]) for row in rows}
    assert all(v > 1.2 for v in sr.values()), sr
