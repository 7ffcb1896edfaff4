"""Adaptive refinement of volume registration (femreg.volume_refine): the marking of femreg.refine on the face
jumps of hexahedra, nested tensor meshes on voxel-cell boundaries, and a refined solve near a strain step."""
import dataclasses

import numpy as np
import pytest
from skfem import MeshHex1

from _volumes import affine_field, volume_pair
from femreg.errors import InputError
from femreg.refine import Refinement, refined_axes, slab_scores, slabs_within_budget
from femreg.volume import register_volume
from femreg.volume_refine import (VOLUME_REFINEMENT, as_volume_refinement, face_jumps, mark_volume,
                                  refine_hex_mesh, transfer_3d)

SPACING = (0.02, 0.2, 0.25)
WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])
X0, S_ABOVE, S_BELOW = 3.5, -0.02, -0.005       # the step: axial strain S_ABOVE for x < X0, S_BELOW beyond


@dataclasses.dataclass
class GN:
    """A stand-in for a Gauss-Newton report: one step, converged."""
    nit: int = 1
    status: int = 0
    message: str = ""


@dataclasses.dataclass
class Sol:
    """A stand-in for a solve on a volume mesh: the mesh, its nodal displacement, the report."""
    mesh: object
    u: np.ndarray
    gn: GN = dataclasses.field(default_factory=GN)


def _step(X):
    x = np.asarray(X, float)[:, 0]
    ux = np.where(x < X0, S_ABOVE * (x - X0), S_BELOW * (x - X0))
    return np.column_stack([ux, np.zeros_like(ux), np.zeros_like(ux)])


def _step_error(res):
    ax = [np.unique(res.mesh.p[a]) for a in range(3)]
    P = np.stack(np.meshgrid(*(np.linspace(a[0] + 0.05, a[-1] - 0.05, 40) for a in ax), indexing="ij"),
                 -1).reshape(-1, 3)
    t = np.zeros((len(P), 6))
    t[:, 0] = np.where(P[:, 0] < X0, S_ABOVE, S_BELOW)
    e = np.asarray(res.strain(P))
    return float(np.sqrt(np.sum(WEIGHTS * (e - t) ** 2) / np.sum(WEIGHTS * t ** 2)))


def _mesh(xs, ys, zs):
    return MeshHex1.init_tensor(np.asarray(xs, float), np.asarray(ys, float), np.asarray(zs, float))


def test_slab_scores_and_splits_are_dimension_generic():
    # a jump across the face between x-slabs 1 and 2 marks both; a 2D call gives the rows / columns of before
    jx = np.zeros((2, 2, 2))
    jx[1, 0, 1] = 5.0
    sx, sy, sz = slab_scores([jx, np.zeros((3, 1, 2)), np.zeros((3, 2, 1))])
    assert np.array_equal(sx, [0, 5, 5]) and not sy.any() and not sz.any()
    r, c = slab_scores([np.array([[0.0, 2.0]]), np.array([[1.0], [3.0]])])
    assert np.array_equal(r, [2, 2]) and np.array_equal(c, [3, 3])
    # voxel edges at origin + (k - 0.5) spacing: a 1 mm slab of 0.25 mm voxels halves at a voxel edge
    b = 0.25 * (np.arange(0, 9, 4) - 0.5)
    (nb,), (k,) = refined_axes([b], [np.array([True, False])], (0.25,), (0.0,), (0.4,), 2)
    assert k == 1 and np.allclose(nb, [-0.125, 0.375, 0.875, 1.875])     # 0.5 mm halves: the 0.4 mm floor stops
    # budget: the strongest slab first, then only what fits
    keep = slabs_within_budget([b, b, b], [np.array([True, True])] * 3, [np.array([3.0, 1.0]),
                               np.array([2.0, 0.0]), np.zeros(2)], (0.25,) * 3, (0.0,) * 3, (0.2,) * 3, 1, 12)
    assert keep[0].tolist() == [True, False] and keep[1].tolist() == [False, False]


def test_refined_hex_mesh_is_nested_and_holds_the_coarse_field_exactly():
    h = np.asarray(SPACING)
    axes = [h[a] * (np.arange(0, n + 1, s) - 0.5) for a, (n, s) in enumerate([(100, 50), (20, 5), (16, 4)])]
    mesh = _mesh(*axes)
    new, counts = refine_hex_mesh(mesh, [np.array([True, False]), np.array([False, True, False, False]),
                                         np.zeros(4, bool)], SPACING, (0, 0, 0), (0.2, 0.3, 0.3), levels=2)
    assert counts == [3, 1, 0] and new.t.shape[1] == 5 * 5 * 4
    for a in range(3):          # every break on a voxel-cell boundary
        k = np.unique(new.p[a]) / h[a] + 0.5
        assert np.allclose(k, np.round(k))
    rng = np.random.default_rng(0)
    u = rng.standard_normal(3 * mesh.p.shape[1])
    v = transfer_3d(u, mesh, new)
    from femreg.volume_fields import HexLocator
    pts = rng.uniform([a[0] for a in axes], [a[-1] for a in axes], (50, 3))
    coarse, fine = HexLocator(mesh).sample(u, pts), HexLocator(new).sample(v, pts)
    for c in ("ux", "uy", "uz", "exx", "eyz"):
        assert np.max(np.abs(coarse[c] - fine[c])) < 1e-12
    # affine fields: no jump across any face
    G = rng.standard_normal((3, 3))
    jumps, scale = face_jumps(new, (new.p.T @ G.T).ravel())
    assert scale > 0 and max(float(np.max(j)) for j in jumps) < 1e-12 * scale


def test_volume_refine_option_is_validated():
    assert as_volume_refinement(None) is None and as_volume_refinement(0) is None
    assert as_volume_refinement("default") is None
    assert as_volume_refinement("auto") is VOLUME_REFINEMENT and as_volume_refinement(2).passes == 2
    with pytest.raises(InputError):
        as_volume_refinement("yes")
    with pytest.raises(InputError):
        as_volume_refinement(Refinement(indicator="ncc"))
    with pytest.raises(InputError):
        Refinement(min_size=(0.1, 0.2, 0.3, 0.4))
    assert Refinement(min_size=(0.5, 0.6, 1.0)).min_size == (0.5, 0.6, 1.0)


@pytest.fixture(scope="module")
def step_pair():
    return volume_pair(_step, shape=(400, 30, 24), spacing=SPACING, seed=0)


def test_refined_volume_splits_slabs_at_a_strain_step_and_lowers_the_error(step_pair):
    ref, mov, spacing, origin = step_pair
    kw = dict(spacing=spacing, origin=origin, element_size=1.0, alpha=0.01, roi=None)
    base = register_volume(ref, mov, **kw)
    res = register_volume(ref, mov, refine="auto", **kw)
    assert base.success and res.success, res.message
    xs0, xs = np.unique(base.mesh.p[0]), np.unique(res.mesh.p[0])
    new = np.setdiff1d(np.round(xs, 6), np.round(xs0, 6))
    # measured: 4 x-slabs added, at 1.49, 2.49, 3.49, 4.49 mm (the step at 3.5 mm); no lateral / elevational split
    assert new.size >= 2 and np.min(np.abs(new - X0)) < 0.5 and np.max(np.abs(new - X0)) < 2.1, new
    for a in (1, 2):
        assert np.unique(res.mesh.p[a]).size == np.unique(base.mesh.p[a]).size
    assert res.refinement.passes and "x-" in res.message
    # measured 46.3 % -> 39.1 % (six components, shear twice; 6 x 4 x 4 mm meshed): at least 5 % lower
    e0, e1 = _step_error(base), _step_error(res)
    assert e1 < 0.95 * e0, (e0, e1)


def test_refinement_leaves_an_affine_field_alone():
    shape = (300, 30, 24)
    field, G = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * np.asarray(SPACING) / 2)
    ref, mov, spacing, origin = volume_pair(field, shape=shape, spacing=SPACING, seed=0)
    kw = dict(spacing=spacing, origin=origin, element_size=1.0)
    base, res = register_volume(ref, mov, **kw), register_volume(ref, mov, refine="auto", **kw)
    # nothing stands out of the noise: the mesh and the field are the unrefined ones
    assert res.refinement.passes == [] and res.mesh.t.shape[1] == base.mesh.t.shape[1]
    assert np.array_equal(res.u, base.u)
    # nor inside the slabs: the interior marking's largest score is 0.125 of its cut (the traction rule's 0.05)
    import dataclasses

    marked, score = mark_volume(base.mesh, base.u, dataclasses.replace(VOLUME_REFINEMENT, interior=True))
    assert not any(m.any() for m in marked) and max(float(s.max()) for s in score) < 0.3


def test_interior_marking_catches_a_slab_without_face_jump():
    # 1 % uniform compression plus an in-plane strain bump e_xx = -e_yy = 0.002 exp(-(z / 3 mm)^2) peaking inside
    # the central z-slab, its shear cancelled by u_z: the z-faces' jumps [[A]] n stay small (the traction rule
    # leaves every z-slab, the central one at 0.42 of its cut), the second difference of the centre strains
    # peaks there (5.31 of its cut, its neighbours 2.60)
    import dataclasses

    m = _mesh(np.linspace(-0.5, 0.5, 5), np.linspace(-0.5, 0.5, 5), np.linspace(-8.75, 8.75, 8))
    x, y, z = m.p
    f = 0.002 * np.exp(-(z / 3.0) ** 2)
    fp = -2.0 * z / 9.0 * f
    u = np.empty(3 * x.size)
    u[0::3], u[1::3] = x * (f - 0.01), y * (0.005 - f)
    u[2::3] = -(x ** 2 - y ** 2) * fp / 2 + 0.005 * z
    plain, score = mark_volume(m, u, VOLUME_REFINEMENT)
    assert not plain[2].any() and score[2][3] < 0.6
    marked, score = mark_volume(m, u, dataclasses.replace(VOLUME_REFINEMENT, interior=True))
    assert marked[2][3] and int(np.argmax(score[2])) == 3 and score[2][3] > 3.0


def test_interior_marking_is_volumes_only():
    from femreg.refine import as_refinement

    with pytest.raises(InputError):
        as_refinement(Refinement(interior=True))


def test_plane_option_is_validated_and_volumes_only():
    from femreg.refine import as_refinement

    for bad in (np.nan, np.inf, True, "0"):
        with pytest.raises(InputError):
            Refinement(plane=bad)
    with pytest.raises(InputError):
        as_refinement(Refinement(plane=0.0))
    assert as_volume_refinement(Refinement(plane=0.0, relax=None)).plane == 0.0
    from femreg.volume_refine import PLANE_REFINEMENT

    assert as_volume_refinement(PLANE_REFINEMENT) is PLANE_REFINEMENT
    with pytest.raises(InputError):
        as_refinement(PLANE_REFINEMENT)


def test_plane_breaks_cut_one_voxel_cell_around_the_plane():
    from femreg.volume_refine import plane_breaks

    zb = np.linspace(-8.75, 8.75, 8)                # voxel planes every 0.5 mm from -8.5 mm: cells end at +-0.25
    new = plane_breaks(zb, 0.0, 0.5, -8.5)
    assert np.allclose(np.setdiff1d(new, zb), [-0.25, 0.25]) and new.size == zb.size + 2
    assert np.array_equal(plane_breaks(new, 0.1, 0.5, -8.5), new)          # already cut: unchanged
    # the nearest voxel plane to 1.9 mm is 2.0 mm: its cell 1.75..2.25 inside the slab 1.25..3.75
    assert np.allclose(np.setdiff1d(plane_breaks(zb, 1.9, 0.5, -8.5), zb), [1.75, 2.25])
    with pytest.raises(InputError):
        plane_breaks(zb, 9.5, 0.5, -8.5)


def test_plane_refinement_leaves_the_other_z_slabs_and_keeps_the_budget():
    # the field of test_interior_marking_catches_a_slab_without_face_jump plus an axial strain step at x = 0
    # (e_xx 0.2 % higher for x < 0): the interior marking splits the two x-slabs beside the step and several
    # z-slabs; with plane=0 only the voxel cell around z = 0 is cut out of the z-slabs, and the element budget
    # counts that cut
    from femreg.volume_refine import refine_volume_passes

    zs = np.linspace(-8.75, 8.75, 8)
    m = _mesh(np.linspace(-0.5, 0.5, 5), np.linspace(-0.5, 0.5, 5), zs)           # 4 x 4 x 7 = 112 elements
    x, y, z = m.p
    f = 0.002 * np.exp(-(z / 3.0) ** 2)
    u = np.empty(3 * x.size)
    u[0::3], u[1::3] = x * (f - 0.01) + np.where(x < 0, -0.002 * x, 0.0), y * (0.005 - f)
    u[2::3] = (x ** 2 - y ** 2) * z / 9.0 * f + 0.005 * z
    spacing, origin = (0.05, 0.05, 0.5), (-0.475, -0.475, -8.5)
    opts = dataclasses.replace(VOLUME_REFINEMENT, interior=True, max_growth=None, min_size=(0.1, 0.1, 1.0))

    def run(o):
        return refine_volume_passes(Sol(m, u), o, lambda mesh, u0: Sol(mesh, u0), spacing, origin)

    def n_axis(sol, a):
        return np.unique(sol.mesh.p[a]).size - 1

    free, _ = run(opts)
    # measured: x 4 -> 6 slabs (each slab beside the step halved once: 0.25 mm = 5 voxel cells -> 2 + 3),
    # z 7 -> 10 slabs
    assert n_axis(free, 0) == 6 and n_axis(free, 2) > 9
    sol, rec = run(dataclasses.replace(opts, plane=0.0))
    assert np.allclose(np.setdiff1d(np.unique(sol.mesh.p[2]), zs), [-0.25, 0.25])
    assert rec.passes[0]["slices"] == 2 and n_axis(sol, 0) == 6
    # 1.7x the elements (190): with the plane's 9 z-slabs, one x-slab fits (5 x 4 x 9 = 180), two would not (216)
    tight, _ = run(dataclasses.replace(opts, plane=0.0, max_growth=1.7))
    assert tight.mesh.t.shape[1] <= 1.7 * m.t.shape[1] and n_axis(tight, 0) == 5 and n_axis(tight, 2) == 9


def test_even_split_reaches_the_smallest_size_where_halving_stops():
    from femreg.volume_refine import even_axes

    # 0.3 mm voxel cells from 0 mm: a 6-cell and a 7-cell slab, 0.6 mm (2 cells) the smallest size
    breaks, marked = [np.array([0.0, 1.8, 3.9])], [np.array([True, True])]
    args = ((0.3,), (0.15,), (0.6,), 2)
    halved, n_h = refined_axes(breaks, marked, *args)
    even, n_e = even_axes(breaks, marked, *args)
    assert np.allclose(halved[0], [0, 0.9, 1.8, 2.4, 3.0, 3.9]) and n_h == [3]      # 0.9 mm halves stay
    assert np.allclose(even[0], [0, 0.6, 1.2, 1.8, 2.4, 3.3, 3.9]) and n_e == [4]
    # one level: two pieces at most; unmarked slabs and slabs below two smallest sizes untouched
    one, _ = even_axes(breaks, [np.array([1, 0])], *args)
    assert np.allclose(one[0], [0, 0.9, 1.8, 3.9])
    same, n0 = even_axes([np.array([0.0, 0.9])], [np.array([True])], *args)
    assert np.allclose(same[0], [0, 0.9]) and n0 == [0]
    from femreg.refine import as_refinement

    with pytest.raises(InputError):
        as_refinement(Refinement(even=True))


def test_strong_halves_the_slabs_just_over_the_cut_once_on_volumes():
    # an axial strain step at x = 0 marks the two 0.4 mm x-slabs beside it (8 voxel cells of 0.05 mm each)
    from femreg.volume_refine import refine_volume_passes

    m = _mesh(np.linspace(-0.8, 0.8, 5), np.linspace(-0.8, 0.8, 5), np.linspace(-0.8, 0.8, 5))
    x = m.p[0]
    u = np.zeros(3 * x.size)
    u[0::3] = np.where(x < 0, -0.02 * x, -0.005 * x)
    spacing, origin = (0.05, 0.05, 0.05), (-0.775, -0.775, -0.775)
    opts = dataclasses.replace(VOLUME_REFINEMENT, max_growth=None, min_size=(0.1, 0.1, 0.1))

    def n_x(o):
        sol, _ = refine_volume_passes(Sol(m, u), o, lambda mesh, u0: Sol(mesh, u0), spacing, origin)
        return np.unique(sol.mesh.p[0]).size - 1, np.unique(sol.mesh.p[1]).size - 1

    # twice (0.1 mm) without strong; once (0.2 mm) where the score is under strong; y- and z-slabs left alone
    assert n_x(opts) == (10, 4)
    assert n_x(dataclasses.replace(opts, strong=1e6)) == (6, 4)
    assert n_x(dataclasses.replace(opts, strong=1.0)) == (10, 4)
