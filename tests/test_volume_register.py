"""Volume registration (femreg.volume, femreg.voxels): the voxel image term against scikit-fem's own shape
functions, the 3D regularisers against finite differences and analytic energies, 2D-vs-3D consistency, exact
affine fields end to end, the result API."""
import numpy as np
import pytest
import scipy.sparse as sp
from skfem import Basis, ElementHex1, MeshHex1, MeshQuad1

import femreg
from femreg import _kernels
from femreg.errors import FileFormatError, InputError
from femreg.regularizers import make_regularizer
from femreg.regularizers.momentum import hourglass_operator
from femreg.volume_result import load_volume_result
from femreg.voxels import SplineVolume, VoxelGrid, VoxelSSDTerm, roi_mesh_3d

from _volumes import affine_field, volume_pair

SPACING = (0.02, 0.2, 0.25)
WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])       # shear components counted twice (femreg.metrics convention)


def _true_strain(G):
    E = 0.5 * (G + G.T)
    return np.array([E[0, 0], E[1, 1], E[2, 2], E[0, 1], E[0, 2], E[1, 2]])


def _total_error(res, G, margin=1.0):
    pts = res.voxel_points()
    ext = np.asarray(res.shape) * res.spacing
    m = np.all((pts > margin) & (pts < ext - margin), axis=1)
    e = res.strain(pts[m])
    t = _true_strain(G)
    return float(np.sqrt(np.nanmean(np.sum(WEIGHTS * (e - t) ** 2, axis=1)) / np.sum(WEIGHTS * t ** 2)))


@pytest.fixture(scope="module")
def small_term():
    rng = np.random.default_rng(3)
    shape = (60, 20, 16)
    I1, I2 = (SplineVolume(rng.standard_normal(shape), SPACING) for _ in range(2))
    mesh = roi_mesh_3d(shape, SPACING, element_size=1.0, margin=0.5)
    return VoxelSSDTerm(VoxelGrid(mesh, shape, SPACING, (0, 0, 0)), I1, I2), mesh, rng


@pytest.fixture(scope="module")
def affine_pair():
    shape = (300, 30, 24)
    field, G = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * SPACING / 2)
    ref, mov, spacing, origin = volume_pair(field, shape=shape, f_mhz=7.0, seed=0)
    return ref, mov, spacing, G


# -- the voxel image term ------------------------------------------------------------------------------------

def test_voxel_term_gradient_and_hessian_are_J_transpose_products_of_skfem_shape_functions(small_term):
    term, mesh, rng = small_term
    n = mesh.p.shape[1]
    u = 0.05 * rng.standard_normal(3 * n)
    P = Basis(mesh, ElementHex1()).probes(term.grid.points().T).tocsr()         # scikit-fem's trilinear hats
    U = term.displacement_at_voxels(u)
    for c in range(3):
        assert np.max(np.abs(P @ u[c::3] - U[c].ravel())) < 1e-13
    g = [a.ravel() for a in term.g]
    J = sp.lil_matrix((P.shape[0], 3 * n))
    for c in range(3):
        J[:, c::3] = sp.diags(g[c]) @ P
    J = J.tocsr()
    r = term.residual(u).ravel()
    grad = J.T @ (term.w0 * r)
    assert np.max(np.abs(grad - term.gradient(u))) < 1e-12 * np.max(np.abs(grad))
    H = (J.T @ J) * term.w0
    assert abs(H - term.hessian()).max() < 1e-12 * abs(H).max()


def test_reference_gradient_at_voxels_is_the_splines_gradient(small_term):
    # the closed-form knot stencil against a central difference of the same spline (error h^2 / 6 times the third derivative)
    term, _, _ = small_term
    I1 = SplineVolume(np.random.default_rng(3).standard_normal(term.moving.shape), SPACING)   # the first draw
    fd = I1.gradient(term.grid.points())
    for a in range(3):
        assert np.max(np.abs(fd[:, a] - term.g[a].ravel())) < 1e-5 * np.max(np.abs(term.g[a]))


@pytest.mark.skipif(not _kernels.HAVE_NUMBA, reason="numba not installed")
def test_compiled_tricubic_warp_equals_map_coordinates(small_term):
    term, mesh, rng = small_term
    u = 0.3 * rng.standard_normal(3 * mesh.p.shape[1])            # some voxels leave the volume: 0 there
    with _kernels.compiled(True):
        a = term.warped_moving(u)
    with _kernels.compiled(False):
        b = term.warped_moving(u)
    assert np.max(np.abs(a - b)) < 1e-12 * np.max(np.abs(b))


def test_warp_of_a_translation_is_the_shifted_volume():
    # a volume that is a cubic polynomial is reproduced exactly by its spline away from the edges
    shape, sp3 = (30, 20, 16), (0.1, 0.2, 0.25)
    X = np.meshgrid(*(np.arange(n) * h for n, h in zip(shape, sp3)), indexing="ij")
    f = lambda x, y, z: 0.3 * x ** 2 - y * z + 0.1 * z ** 3 + x          # noqa: E731
    I = SplineVolume(f(*X), sp3)
    mesh = roi_mesh_3d(shape, sp3, element_size=1.0, margin=0.8)
    term = VoxelSSDTerm(VoxelGrid(mesh, shape, sp3, (0, 0, 0)), I, I)
    t = np.array([0.037, -0.051, 0.073])
    u = np.tile(t, mesh.p.shape[1])
    pts = term.grid.points()
    want = f(*(pts + t).T).reshape(term.shape)
    assert np.max(np.abs(term.warped_moving(u) - want)) < 1e-3 * np.max(np.abs(want))


# -- the regularisers on hexahedra -----------------------------------------------------------------------------

def _affine_nodal(mesh, G, b=(0.1, -0.2, 0.05)):
    return (G @ mesh.p + np.asarray(b)[:, None]).T.ravel()


@pytest.mark.parametrize("name,kw", [("momentum-stress", {"hourglass": 1000.0, "dilatation": "centre"}),
                                     ("momentum-strain", {}), ("strain", {}), ("strain-incompressible", {})])
def test_3d_regulariser_gradient_is_the_derivative_of_its_energy(name, kw):
    rng = np.random.default_rng(1)
    mesh = MeshHex1.init_tensor(np.linspace(0, 3, 4), np.linspace(0, 2, 3), np.array([0.0, 1.5, 3.0]))
    r = make_regularizer(name, **kw)
    r.setup(mesh)
    u = 0.01 * rng.standard_normal(3 * mesh.p.shape[1])
    v = rng.standard_normal(u.size)
    h = 1e-6
    fd = (r.energy(u + h * v) - r.energy(u - h * v)) / (2 * h)
    assert abs(fd - r.gradient(u) @ v) < 1e-5 * abs(fd) + 1e-12
    H = r.hessian(u)
    assert H.shape == (u.size, u.size) and abs(H - H.T).max() < 1e-10 * abs(H).max()


def test_3d_momentum_jumps_vanish_on_affine_fields_and_hourglass_control_sees_only_hourglass_modes():
    rng = np.random.default_rng(2)
    mesh = MeshHex1.init_tensor(np.linspace(0, 4, 5), np.linspace(0, 3, 4), np.linspace(0, 2, 3))
    r = make_regularizer("momentum-stress", hourglass=1.0)
    r.setup(mesh)
    u = _affine_nodal(mesh, 0.01 * rng.standard_normal((3, 3)))
    assert np.max(np.abs(r.operator @ u)) < 1e-14
    Gh = hourglass_operator(mesh)
    assert Gh.shape == (12 * mesh.t.shape[1], 3 * mesh.p.shape[1])
    assert np.max(np.abs(Gh @ u)) < 1e-14
    # the checkerboard (+-1 at alternate nodes) is an hourglass mode: the jumps of A n at face centres miss part of
    # it, the hourglass operator does not
    par = (np.round(mesh.p[0]) + np.round(mesh.p[1]) + np.round(mesh.p[2])) % 2
    w = np.zeros(3 * mesh.p.shape[1])
    w[1::3] = np.where(par == 0, 1.0, -1.0)
    assert np.linalg.norm(Gh @ w) > 1.0


def test_3d_strain_energy_of_an_affine_field_is_the_analytic_integral():
    G = np.array([[-0.01, 0.004, 0.0], [0.002, 0.005, -0.001], [0.0, 0.003, 0.005]])
    mesh = MeshHex1.init_tensor(np.linspace(0, 4, 3), np.linspace(0, 3, 4), np.linspace(0, 2, 2))
    E = 0.5 * (G + G.T)
    for name, want in (("strain", 0.5 * np.sum(E * E) * 24.0),
                       ("strain-incompressible", 0.5 * (np.sum(E * E) + 100.0 * np.trace(E) ** 2) * 24.0)):
        r = make_regularizer(name, alpha=1.0)
        r.setup(mesh)
        assert r.energy(_affine_nodal(mesh, G)) == pytest.approx(want, rel=1e-12)


def test_momentum_on_an_extruded_mesh_is_the_2d_regulariser_times_the_thickness():
    # u(x, y) with u_z = 0 on a mesh extruded along z: the jumps of A n across the side faces are the 2D edge
    # jumps (same lambda_bar), the z faces see no jump, so R_3D = L_z R_2D (delta made negligible)
    rng = np.random.default_rng(4)
    xs, ys, zs = np.linspace(0, 4, 5), np.array([0.0, 0.7, 1.5, 2.6, 3.0]), np.array([0.0, 1.0, 2.5])
    m2, m3 = MeshQuad1.init_tensor(xs, ys), MeshHex1.init_tensor(xs, ys, zs)
    u2 = 0.01 * rng.standard_normal(2 * m2.p.shape[1])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    # nodal values of the extruded field from the 2D nodes at the same (x, y)
    i2 = {(round(a, 9), round(b, 9)): k for k, (a, b) in enumerate(m2.p.T)}
    k3 = np.array([i2[(round(a, 9), round(b, 9))] for a, b in m3.p[:2].T])
    u3 = np.zeros(3 * m3.p.shape[1])
    u3[0::3], u3[1::3] = u2[0::2][k3], u2[1::2][k3]
    for kw in ({"lambda_bar": 9.0, "dilatation": "centre"}, {"lambda_bar": 2.0, "dilatation": "edge"}):
        r2 = make_regularizer("momentum-strain", alpha=1.0, delta=1e-30, **kw)
        r3 = make_regularizer("momentum-strain", alpha=1.0, delta=1e-30, **kw)
        r2.setup(m2)
        r3.setup(m3)
        assert r3.energy(u3) == pytest.approx(2.5 * r2.energy(u2), rel=1e-10)


def test_3d_alpha_is_scaled_by_element_volume():
    from femreg.scaling import alpha_scale

    m = MeshHex1.init_tensor(np.linspace(0, 4, 5), np.linspace(0, 4, 5), np.linspace(0, 4, 3))   # 1 x 1 x 2 mm
    assert alpha_scale(m) == pytest.approx(8.0 / 2.0)


# -- registration ----------------------------------------------------------------------------------------------

def test_volume_constant_along_z_gives_the_2d_answer():
    # R_eps (quadratic), zero start, no repair: the 3D objective is L_z times the 2D one, so the Gauss-Newton
    # iterates are the 2D ones with u_z = 0
    field, G = affine_field(0.008, 0.003, 0.0, centre=(2.0, 2.0, 0.0))
    ref3, mov3, spacing, _ = volume_pair(field, shape=(200, 20, 1), spacing=(0.02, 0.2, 0.25), f_mhz=7.0,
                                         elev_fwhm=0.5, seed=6)
    ref2, mov2 = ref3[:, :, 0], mov3[:, :, 0]
    nz = 10
    R, M = np.repeat(ref3, nz, axis=2), np.repeat(mov3, nz, axis=2)
    kw = dict(regularizer="strain", alpha=5.0, initial="zero", repair=False, maxiter=8)
    r3 = femreg.register(R, M, spacing=spacing, element_size=(1.0, 1.0, 2.0), margin=(0.5, 0.5, 0.25), **kw)
    r2 = femreg.register(ref2, mov2, spacing=spacing[:2], element_size=(1.0, 1.0), margin=(0.5, 0.5), roi=None,
                         check_orientation=False, **kw)
    assert r3.nit == r2.nit and r2.nit >= 2
    pts = r2.mesh.p.T
    for z in (0.25, 1.0, 2.1):
        d3 = r3.displacement(np.column_stack([pts, np.full(len(pts), z)]))
        assert np.max(np.abs(d3[:, :2] - r2.displacement(pts))) < 1e-9
        assert np.max(np.abs(d3[:, 2])) < 1e-8       # measured 2.3e-10: u_z is fixed only by the solver shift
    assert r3.strain_components[:2] == ("exx", "eyy") and r3.strain_components[3] == "exy"


def test_exact_affine_field_3d(affine_pair):
    ref, mov, spacing, G = affine_pair
    res = femreg.register(ref, mov, spacing=spacing, element_size=1.0)
    assert res.success, res.message
    # measured 2.50 % (7 MHz, compression 1 %, shear 0.5 %, rotation 0.5 deg, 6 x 6 x 6 mm); margin 1.3x
    err = _total_error(res, G)
    assert err < 0.033, err
    assert res.ncc_after > 0.99 and res.quality.shape == (res.mesh.t.shape[1],)
    assert res.strain(np.array([[3.0, 3.0, 3.0]])).shape == (1, 6)
    assert res.strain(np.array([[3.0, 3.0, 3.0]]), "element").shape == (1, 6)


def test_volume_result_grid_save_load_and_vtu(affine_pair, tmp_path):
    ref, mov, spacing, _ = affine_pair
    res = femreg.register(ref, mov, spacing=spacing, element_size=2.0, maxiter=3)
    g = res.on_grid()
    for k in ("ux", "uy", "uz", "exx", "eyy", "ezz", "exy", "exz", "eyz", "quality"):
        assert g[k].shape == ref.shape
    assert set(g) == {"ux", "uy", "uz", "exx", "eyy", "ezz", "exy", "exz", "eyz", "quality"}
    assert np.allclose(res.spacing, spacing) and res.origin.shape == (3,)
    inside = np.isfinite(g["ux"])
    assert 0.25 < inside.mean() < 1.0 and np.all(np.isfinite(g["quality"][inside]))
    p = res.save(tmp_path / "v.npz")
    back = femreg.load_result(p)           # the one reader dispatches on the file kind
    assert isinstance(back, femreg.VolumeResult)
    pts = np.array([[2.0, 2.5, 3.0], [4.0, 3.0, 2.0]])
    assert np.array_equal(back.displacement(pts), res.displacement(pts))
    assert back.success == res.success and back.message == res.message
    (tmp_path / "x.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(FileFormatError):
        load_volume_result(tmp_path / "x.npz")
    meshio = pytest.importorskip("meshio")
    v = meshio.read(res.write_vtu(tmp_path / "v.vtu"))
    assert v.cells[0].type == "hexahedron" and v.point_data["u"].shape == (res.mesh.p.shape[1], 3)
    assert np.allclose(v.point_data["u"], res.u.reshape(-1, 3))
    # VTK's hexahedron order: every cell has positive volume (the corners of its bottom face counter-clockwise)
    c = v.points[v.cells[0].data]                                          # (n_el, 8, 3)
    assert np.all(np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]), c[:, 4] - c[:, 0]) > 0)
    pytest.importorskip("h5py")
    x = meshio.read(res.write_xdmf(tmp_path / "v.xdmf"))
    assert np.allclose(x.point_data["exx"], res.nodal_strain[:, 0])


def test_bad_volume_input_is_a_clear_error(affine_pair):
    ref, mov, spacing, _ = affine_pair
    with pytest.raises(InputError, match="spacing"):
        femreg.register(ref, mov, spacing=(0.02, 0.2))
    with pytest.raises(InputError, match="shape mismatch"):
        femreg.register(ref, mov[:-1], spacing=spacing)
    bad = ref.copy()
    bad[3, 3, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        femreg.register(bad, mov, spacing=spacing)
    with pytest.raises(InputError, match="roi"):
        femreg.register(ref, mov, spacing=spacing, roi=(0, 1, 0, 1))


def test_track_volumes_accumulates_increments(affine_pair):
    ref, mov, spacing, G = affine_pair
    # frames 0, 1, 0: the accumulated field returns to ~0
    tr = femreg.track([ref, mov, ref], spacing=spacing, element_size=2.0)
    assert tr.success and len(tr) == 2
    pts = np.array([[3.0, 3.0, 3.0]])
    e1 = tr.accumulated[0].strain(pts)[0]
    assert abs(e1[0] - _true_strain(G)[0]) < 0.1 * abs(_true_strain(G)[0])
    assert np.max(np.abs(tr.accumulated[1].strain(pts))) < 0.05 * np.max(np.abs(_true_strain(G)))


@pytest.mark.slow
@pytest.mark.parametrize("f_mhz", [3.0, 7.5, 15.0])
def test_exact_affine_field_3d_per_probe(f_mhz):
    dx = min(0.02, 1.54 / (2 * 4 * f_mhz))                       # RF sampled at >= 4 f0
    shape = (int(round(10.0 / dx)), 40, 32)                     # 10 x 8 x 8 mm
    spacing = (dx,) + SPACING[1:]
    field, G = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * spacing / 2)
    ref, mov, spacing, _ = volume_pair(field, shape=shape, spacing=spacing, f_mhz=f_mhz, seed=11)
    res = femreg.register(ref, mov, spacing=spacing)
    assert res.success, res.message
    # the target (2 %); measured 1.89 / 0.83 / 1.22 % at 3 / 7.5 / 15 MHz (the 20 x 20 x 15 mm benchmark volume:
    # 0.18 / 0.31 / 0.33 % at 3 / 7 / 15 MHz)
    assert _total_error(res, G, margin=2.0) < 0.02
    assert femreg.repair.hopped_fraction(res.hop_gain) == 0.0     # no element one RF period off


def test_cli_registers_and_tracks_volume_files(affine_pair, tmp_path, capsys):
    from femreg.cli import main

    ref, mov, spacing, G = affine_pair
    seq = tmp_path / "seq.npz"
    np.savez(seq, rf=np.stack([ref, mov]), spacing=np.asarray(spacing))
    out = tmp_path / "r.npz"
    assert main(["register", str(seq), "-o", str(out), "--element-size", "2"]) == 0
    res = load_volume_result(out)
    e = res.strain(np.array([[3.0, 3.0, 3.0]]))[0]
    assert abs(e[0] - _true_strain(G)[0]) < 0.1 * abs(_true_strain(G)[0])
    capsys.readouterr()
    assert main(["track", str(seq), "-o", str(tmp_path / "t"), "--element-size", "2"]) == 0
    assert (tmp_path / "t" / "frame_001.npz").exists()
    assert "femreg track: 1 volume in" in capsys.readouterr().out          # one volume tracked: singular
    bad = tmp_path / "bad.npz"
    np.savez(bad, rf=ref[:, :, 0], spacing=np.asarray(spacing))
    assert main(["register", str(bad), "-o", str(out)]) == 2
    assert "volume" in capsys.readouterr().err


def test_cli_reads_metaimage_and_mat_volumes(affine_pair, tmp_path, capsys):
    """Volumes as scanners and MATLAB write them: a MetaImage of NDims 4 and a MAT-file with three spacing values
    are volumes without a flag; two NDims-3 MetaImage files are volumes with --volume, and without it their first
    frames are registered with a note that says so."""
    from femreg.cli import main
    from femreg.io import save_volumes

    ref, mov, spacing, G = affine_pair
    truth = _true_strain(G)[0]
    out = tmp_path / "r.npz"
    for name in ("seq.mhd", "seq.mat"):
        save_volumes(tmp_path / name, np.stack([ref, mov]), spacing)
        assert main(["register", str(tmp_path / name), "-o", str(out), "--element-size", "2"]) == 0, name
        e = load_volume_result(out).strain(np.array([[3.0, 3.0, 3.0]]))[0]
        assert abs(e[0] - truth) < 0.1 * abs(truth), (name, e[0], truth)
    save_volumes(tmp_path / "ref.mhd", ref, spacing)
    save_volumes(tmp_path / "mov.mhd", mov, spacing)
    argv = ["register", str(tmp_path / "ref.mhd"), str(tmp_path / "mov.mhd"), "-o", str(out), "--element-size", "2"]
    capsys.readouterr()
    assert main(argv + ["--volume"]) == 0
    assert load_volume_result(out).strain(np.array([[3.0, 3.0, 3.0]])).shape == (1, 6)
    main(argv + ["--no-orientation-check"])          # read as frames: frame 0 of each, and a note says so
    err = capsys.readouterr().err
    assert f"holds {ref.shape[2]} and" in err and "--volume" in err, err


@pytest.mark.parametrize("method", ["auto", "splu", "pardiso"])
def test_sparse_solver_branches_solve_a_3d_gauss_newton_system(method):
    from femreg.linsolve import SPDSolver, have_pardiso

    if method == "pardiso" and not have_pardiso():
        pytest.skip("pypardiso not installed")
    mesh = MeshHex1.init_tensor(np.linspace(0, 4, 6), np.linspace(0, 3, 5), np.linspace(0, 2, 4))
    r = make_regularizer("momentum-stress", hourglass=1000.0)
    r.setup(mesh)
    rng = np.random.default_rng(8)
    u = 1e-3 * rng.standard_normal(3 * mesh.p.shape[1])
    H = (r.hessian(u) + sp.identity(u.size)).tocsc()
    b = rng.standard_normal(u.size)
    s = SPDSolver(method, shift=0.0, band_limit=10 if method == "auto" else 25_000_000, large_method="pardiso")
    x = s.solve(H, b)
    assert np.linalg.norm(H @ x - b) < 1e-8 * np.linalg.norm(b)
    if method == "auto":     # band above the limit: the sparse branch (PARDISO when installed, else SuperLU)
        assert s.last_method == ("pardiso" if have_pardiso() else "splu")


def test_user_forms_work_on_hexahedra():
    from skfem import BilinearForm, LinearForm
    from skfem.helpers import div, dot, grad

    from femreg.regularizers import from_form, from_jump_forms

    xs = np.linspace(0.0, 4.0, 5)                       # 4 elements of 1 mm along x
    mesh = MeshHex1.init_tensor(xs, np.linspace(0, 3, 3), np.linspace(0, 2, 3))
    G = np.array([[-0.01, 0.004, 0.0], [0.002, 0.005, -0.001], [0.0, 0.003, 0.005]])
    r = from_form(BilinearForm(lambda u, v, w: div(u) * div(v)), alpha=2.0, quadrature="centre")
    r.setup(mesh)
    assert r.energy(_affine_nodal(mesh, G)) == pytest.approx(0.5 * 2.0 * np.trace(G) ** 2 * 24.0, rel=1e-12)
    # jump of d u_x / dn across the faces: u_x = x^2 interpolated trilinearly has slope x_i + x_{i+1} in element
    # i, so each of the 3 interior x planes (3 x 2 mm) jumps by 2; the y and z faces see d u_x / dy = dz = 0
    tv = from_jump_forms(LinearForm(lambda v, w: dot(grad(v)[0], w.n)), alpha=1.0, delta=1e-30)
    tv.setup(mesh)
    u = np.zeros(3 * mesh.p.shape[1])
    u[0::3] = mesh.p[0] ** 2
    assert tv.energy(u) == pytest.approx(3 * 6.0 * 2.0, rel=1e-10)
    assert tv.energy(_affine_nodal(mesh, G)) < 1e-12


def test_a_volume_one_element_thick_is_flagged_not_returned_as_measured():
    # one 2 mm element across a 3 mm thick volume: its elevational strain rests on that element alone
    field, _ = affine_field(centre=(2.5, 2.8, 1.5))
    ref, mov, spacing, _ = volume_pair(field, shape=(250, 28, 12), f_mhz=7.0, seed=1)
    res = femreg.register(ref, mov, spacing=spacing)
    assert not res.success
    assert "only one element across the elevational extent" in res.message


def test_a_transposed_volume_is_refused_not_registered(affine_pair):
    # lateral and axial axes exchanged (and their spacings with them): the carrier runs along axis 1
    from femreg.orientation import OrientationError

    ref, mov, spacing, _ = affine_pair
    t = (np.swapaxes(ref, 0, 1).copy(), np.swapaxes(mov, 0, 1).copy())
    swapped = (spacing[1], spacing[0], spacing[2])
    with pytest.raises(OrientationError, match="transposed") as err:
        femreg.register(*t, spacing=swapped)
    # the advice is the volume's own: its transpose and its three spacings, not a frame's
    msg = str(err.value)
    assert "volume.transpose(1, 0, 2)" in msg and "frame.T" not in msg
    assert f"({spacing[0]:g}, {spacing[1]:g}, {spacing[2]:g}) mm" in msg
    with pytest.raises(OrientationError, match=r"volumes\.transpose\(0, 2, 1, 3\)"):
        femreg.track(np.stack(t), spacing=swapped)
    # the check can be switched off, as in 2D: then the pair is registered (here, the wrong way round)
    res = femreg.register(*t, spacing=swapped, check_orientation=False, maxiter=1)
    assert res.u.shape == (3 * res.mesh.p.shape[1],)


def test_swapped_spacing_on_a_volume_names_the_three_spacings_to_pass(affine_pair):
    # axial and lateral spacings exchanged, the array itself right: the advice keeps dz in third place
    from femreg.orientation import OrientationError

    ref, mov, spacing, _ = affine_pair
    wrong = (spacing[1], spacing[0], spacing[2])
    with pytest.raises(OrientationError) as err:
        femreg.register(ref, mov, spacing=wrong)
    msg = str(err.value)
    assert f"pass spacing ({spacing[0]:g}, {spacing[1]:g}, {spacing[2]:g}) (axial, lateral, elevational" in msg
    assert f"--spacing {spacing[0]:g} {spacing[1]:g} {spacing[2]:g})" in msg
