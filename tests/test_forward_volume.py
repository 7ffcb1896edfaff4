"""3D RF volume simulator: PSF against its parameters and a direct sum, speckle, warps, noise, fields."""
import math

import numpy as np
import pytest

from femreg.speckle import envelope
from forward.volume import (PSF3D, Affine3D, FEVolumeField, FunctionField3D, ImagingVolume, VolumeProbe,
                            make_volume_pair, make_volume_sequence, render_volume)

C = 1.54e6  # mm/s
PSF_F = PSF3D(7e6, 2.365 / 7e6, 0.9, 2.0, lateral_focus_mm=12.0, elevational_focus_mm=12.0)
GRID = ImagingVolume((400, 60, 50), (0.025, 0.1, 0.1), (5.0, -3.0, -2.5))


def _fwhm(p, d):
    """FWHM of a sampled single-peaked profile, edges by linear interpolation."""
    p = p / p.max()
    above = np.flatnonzero(p >= 0.5)
    lo, hi = above[0], above[-1]
    return (hi + (p[hi] - 0.5) / (p[hi] - p[hi + 1]) - lo + (p[lo] - 0.5) / (p[lo] - p[lo - 1])) * d


def _gaussian_beam_fwhm(fwhm0, focus, depth, f0):
    """Textbook Gaussian beam: pulse-echo sigma s0 = FWHM / 2.355, one-way waist w0 = 2 s0, Rayleigh range
    pi w0^2 / lambda, width growing as sqrt(1 + (d / z_R)^2)."""
    s0 = fwhm0 / (2 * math.sqrt(2 * math.log(2)))
    z_r = math.pi * (2 * s0) ** 2 / (C / f0)
    return fwhm0 * math.sqrt(1 + ((depth - focus) / z_r) ** 2)


def _envelope3(v):
    return envelope(v.reshape(v.shape[0], -1)).reshape(v.shape)


def test_point_response_widths_match_the_psf_parameters():
    """One scatterer at the focus: envelope FWHM axial = c * pulse length / 2, lateral 0.9 mm, elevational 1.2 mm
    (1 % margin: sampling at 0.025 / 0.1 mm and the sub-plane split); 8 mm below the focus both beam widths
    follow the Gaussian-beam widening (2 %)."""
    psf = PSF3D(7e6, 2.365 / 7e6, 0.9, 1.2, lateral_focus_mm=12.0, elevational_focus_mm=12.0)
    grid = ImagingVolume((640, 60, 60), (0.025, 0.1, 0.1), (6.0, -3.0, -3.0))
    for depth, tol in ((12.0, 0.01), (20.0, 0.02)):
        R = render_volume(np.array([[depth + 0.007, 0.013, -0.021]]), np.ones(1), grid, psf, dtype=np.float64)
        env = _envelope3(R)
        i, j, k = np.unravel_index(np.argmax(env), env.shape)
        ax = _fwhm(env[:, j, k], 0.025)
        lat = _fwhm(env[i, :, k], 0.1)
        el = _fwhm(env[i, j, :], 0.1)
        assert abs(ax - C * 2.365 / 7e6 / 2) < 0.01 * ax, (depth, ax)
        want_lat = _gaussian_beam_fwhm(0.9, 12.0, depth, 7e6)
        want_el = _gaussian_beam_fwhm(1.2, 12.0, depth, 7e6)
        assert abs(lat - want_lat) < tol * want_lat, (depth, lat, want_lat)
        assert abs(el - want_el) < tol * want_el, (depth, el, want_el)
    assert want_el > 1.3 and want_lat > 1.2   # the widening is resolved by the checks above


def test_render_matches_a_direct_sum():
    """The factorised renderer against the PSF summed directly at every voxel (elevational width at the voxel's
    depth): within 0.3 % of the peak (measured 0.17 %: depth bands and sub-plane interpolation)."""
    P = np.array([[8.013, 0.037, 0.071], [12.3, -1.02, 0.93], [14.1, 1.33, -0.41]])
    a = np.array([1.0, -0.7, 1.3])
    R = render_volume(P, a, GRID, PSF_F, dtype=np.float64)
    X, Y, Z = np.meshgrid(GRID.x, GRID.y, GRID.z, indexing="ij")
    sx = C * (2.365 / 7e6 / (2 * math.sqrt(2 * math.log(2)))) / 2
    s = 2 * math.sqrt(2 * math.log(2))
    B = np.zeros(GRID.shape)
    for (xs, ys, zs), am in zip(P, a):
        sy = _gaussian_beam_fwhm(0.9, 12.0, xs, 7e6) / s
        sz = np.vectorize(lambda d: _gaussian_beam_fwhm(2.0, 12.0, d, 7e6) / s)(GRID.x)[:, None, None]
        B += (am * np.exp(-0.5 * ((X - xs) / sx) ** 2) * np.cos(4 * np.pi * 7e6 * (X - xs) / C)
              * (0.9 / s / sy) * np.exp(-0.5 * ((Y - ys) / sy) ** 2)
              * (2.0 / s / sz) * np.exp(-0.5 * ((Z - zs) / sz) ** 2))
    err = np.abs(R - B).max() / np.abs(B).max()
    assert err < 3e-3, err


PROBE = VolumeProbe(7.0, 30.8, 0.2, 0.25, 0.9, 2.0, elevation_focus_mm=None)


@pytest.fixture(scope="module")
def shifted():
    shift = np.array([4 * 0.025, 2 * 0.2, 3 * 0.25])   # whole voxels: (4, 2, 3)
    return make_volume_sequence([lambda p: np.tile(shift, (len(p), 1))], PROBE, (6, 8, 8), snr_db=20, seed=3,
                                top_mm=5)


def test_speckle_fully_developed(shifted):
    """Envelope mean / std of the default density: Rayleigh 1.913 within 2 % (measured 1.908)."""
    env = _envelope3(shifted.frames[0])
    r = env.mean() / env.std()
    assert abs(r - 1.913) < 0.02 * 1.913, r


def test_warped_volume_ncc_peak_at_the_known_shift(shifted):
    """A translation by (4, 2, 3) voxels: the NCC of reference and moving volume peaks at that shift among all
    neighbouring integer shifts, at the level noise allows (20 dB: 1 / (1 + 10^-2) = 0.990)."""
    ref, mov = shifted.frames
    best = None
    for a in range(2, 7):
        for b in range(0, 5):
            for c in range(1, 6):
                r = ref[10:-10, 6:-6, 6:-6]
                m = mov[10 + a:ref.shape[0] - 10 + a, 6 + b:ref.shape[1] - 6 + b, 6 + c:ref.shape[2] - 6 + c]
                ncc = float(np.sum(r * m) / np.sqrt(np.sum(r * r) * np.sum(m * m)))
                if best is None or ncc > best[0]:
                    best = (ncc, a, b, c)
    assert best[1:] == (4, 2, 3), best
    assert best[0] > 0.98, best


def test_noise_level_and_seeding(shifted):
    """The same seed gives the same volumes, another seed other speckle; SNR as asked (measured on the clean
    render of frame 0)."""
    f = shifted.fields[1]
    again = make_volume_sequence([f], PROBE, (6, 8, 8), snr_db=20, seed=3, top_mm=5)
    assert np.array_equal(again.frames, shifted.frames)
    other = make_volume_sequence([f], PROBE, (6, 8, 8), snr_db=20, seed=4, top_mm=5)
    assert abs(np.corrcoef(other.frames[0].ravel(), shifted.frames[0].ravel())[0, 1]) < 0.05
    clean = make_volume_sequence([f], PROBE, (6, 8, 8), snr_db=None, seed=3, top_mm=5).frames[0]
    snr = 10 * np.log10(np.mean(clean.astype(float) ** 2) / np.mean((shifted.frames[0] - clean).astype(float) ** 2))
    assert abs(snr - 20.0) < 0.1, snr


def test_affine_field_exact_and_incompressible():
    """u = (F - I)(X - c): strain sym(F - I) equals the finite-difference strain of the displacement; pure
    compression keeps the volume (det F = 1) with equal lateral and elevational expansion."""
    f = Affine3D(0.02, shear={"xy": 0.01, "yz": -0.005}, rotation_deg=(0.0, 1.0, 2.0))
    p = np.random.default_rng(0).uniform(0, 20, (50, 3))
    fd = FunctionField3D(f.displacement).strain(p)
    assert np.allclose(f.strain(p), fd, atol=1e-9)
    c = Affine3D(0.02)
    assert abs(np.linalg.det(c.F) - 1) < 1e-12
    e = c.strain(p[:1])[0]
    assert e[0] == pytest.approx(-0.02) and e[1] == pytest.approx(e[2]) and e[1] > 0.01


def test_pair_of_affine_compression():
    """make_volume_pair: shapes from the probe's spacing, field as given, reference != moving."""
    pr = VolumeProbe(7.0, 30.8, 0.2, 0.25, 0.9, 2.0)
    pair = make_volume_pair(Affine3D(0.01), pr, (3.0, 4.0, 3.0), seed=1, snr_db=None)
    assert pair.ref.shape == (120, 20, 12) and pair.spacing == pytest.approx(pr.spacing)
    assert pair.field.strain(np.zeros((1, 3)))[0, 0] == pytest.approx(-0.01)
    assert not np.allclose(pair.ref, pair.mov)


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="spacing"):
        ImagingVolume((10, 10, 10), (0.1, -1, 0.1))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        render_volume(np.zeros((3, 2)), np.ones(3), GRID, PSF_F)
    with pytest.raises(ValueError, match="fs"):
        VolumeProbe(f0_mhz=20.0, fs_mhz=30.0)


@pytest.fixture(scope="module")
def coarse_3d():
    import forward

    return forward.solve_elasticity("3d", mesh_size_mm=6.0, coarse_size_mm=24.0)


def test_fe_volume_field_gradient_matches_finite_differences(coarse_3d):
    """The full 3D gradient of the (quarter, mirrored) FE solution against central differences of
    displacement_3d, in all four mirrored quadrants (P2: the difference is O(h^2), tiny at h = 1e-3 mm)."""
    f = FEVolumeField(coarse_3d, scale=0.3)
    rng = np.random.default_rng(2)
    p = rng.uniform([5, -20, -20], [60, 20, 20], (40, 3))
    fd = FunctionField3D(f.displacement, h=1e-3).strain(p)
    e = f.strain(p)
    ok = np.all(np.isfinite(e), axis=1)
    assert ok.all()
    assert np.abs(e - fd).max() < 1e-3 * np.abs(e).max(), np.abs(e - fd).max()
    # plane z = 0: the in-plane components equal the 2D strain of the solution
    q = np.column_stack([p[:, :2], np.zeros(len(p))])
    assert np.allclose(f.strain(q)[:, [0, 1, 3]], 0.3 * coarse_3d.strain(p[:, :2]), atol=1e-12)


def test_paper_volume_sequence_schedule_plane_and_cache(tmp_path):
    """The paper's 3D phantom as volumes (coarse FE mesh and probe to stay fast): a plane at z = 0, the true
    mean axial strain over that plane at the paper's frame 7 = -0.8 % (its schedule), the inclusion brighter,
    and the cached file read back identical with the same exact fields."""
    from forward.volume import paper_volume_sequence

    kw = dict(frames=(0, 6), probe=VolumeProbe(3.0, 12.0, 1.0, 1.0, 3.0, 3.0, elevation_focus_mm=30.0),
              depth_mm=40.0, width_mm=20.0, elevation_mm=10.0, snr_db=None, seed=1,
              fe_options=dict(mesh_size_mm=6.0, coarse_size_mm=24.0), cache_dir=tmp_path)
    seq = paper_volume_sequence("HI", **kw)
    g = seq.grid
    assert seq.frames.shape == (2,) + g.shape and g.shape[2] % 2 == 1
    assert np.min(np.abs(g.z)) < 1e-12
    X, Y = np.meshgrid(g.x, g.y, indexing="ij")
    plane = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    assert np.mean(seq.true_strain(1, plane)[:, 0]) == pytest.approx(-0.008, rel=0.02)
    env = _envelope3(seq.frames[0].astype(float))
    r = np.sqrt((g.x[:, None, None] - 30.0) ** 2 + g.y[None, :, None] ** 2 + g.z[None, None, :] ** 2)
    assert env[r < 6].mean() > 1.5 * env[(r > 9) & (r < 15)].mean()       # amplitudes x2 inside the sphere
    again = paper_volume_sequence("HI", **kw)
    assert again.path == seq.path and np.array_equal(again.frames, seq.frames)
    assert np.array_equal(again.true_displacement(1, plane[:50]), seq.true_displacement(1, plane[:50]))
