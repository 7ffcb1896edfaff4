"""Simulated sequences (forward/sequences.py): schedule, motion of the image vs the true field, determinism,
save/load, cache, CLI, bad input.  FE-free (an analytic field with the Solution interface) to stay fast."""
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, spline_filter
from scipy.optimize import minimize

import forward
import forward.sequences as S
from femreg.cli import main
from forward.sequences import AnalyticField, load_sequence, paper_schedule, schedule_figures, simulate_sequence
from forward.ultrasound import envelope, measured_snr_db


class ShiftedField(AnalyticField):
    """Analytic field plus a lateral translation ``shift`` mm per mm of compression (to test lateral motion)."""

    def __init__(self, shift=0.25, **kw):
        super().__init__(**kw)
        self.shift = shift

    def displacement(self, points):
        u = super().displacement(points)
        u[:, 1] += self.shift
        return u


def small(n_frames=3, seed=0, snr_db=12.0, depth_mm=6.0, width_mm=5.0, field=None, **kw):
    field = AnalyticField(40.0) if field is None else field
    return simulate_sequence("plane-strain", "HI", n_frames=n_frames, seed=seed, snr_db=snr_db, depth_mm=depth_mm,
                             width_mm=width_mm, field=field, **kw)


def test_paper_schedule_numbers():
    e = 100 * paper_schedule(20)
    steps = np.diff(e)
    assert e[0] == 0 and abs(e[19] - 7.0) < 1e-9, e[19]
    assert abs(steps.mean() - 0.4) < 0.05, steps.mean()
    assert abs(steps.max() - 0.8) < 1e-9 and np.all(steps > 0), steps
    assert abs(e[6] - 0.8) < 1e-9, f"frames 1 -> 7: {e[6]}"
    assert np.all(np.diff(steps) >= -1e-12), "increments never decrease"
    np.testing.assert_array_equal(100 * paper_schedule(7), e[:7])
    assert abs(100 * paper_schedule(22)[-1] - 8.6) < 1e-9


def test_schedule_measured_from_true_strain():
    seq = small(n_frames=20, snr_db=None, depth_mm=40.0, width_mm=4.0)
    fig = schedule_figures(seq)
    assert abs(fig["total"] - 7.0) < 0.01, fig
    assert abs(fig["mean_step"] - 7.0 / 19) < 0.001 and abs(fig["max_step"] - 0.8) < 0.001, fig
    assert abs(fig["frames_1_7"] - 0.8) < 0.001, fig
    assert seq.frames.shape == (20,) + seq.shape and seq.frames.dtype == np.float32


def _ncc_shift(ref, mov, i, j, hi, hj, guess):
    """(axial, lateral) shift in samples of the window ref[i-hi:i+hi+1, j-hj:j+hj+1] found in ``mov`` by
    maximising the normalised cross-correlation with quintic-spline interpolation of ``mov``."""
    win = ref[i - hi:i + hi + 1, j - hj:j + hj + 1].astype(float)
    coef = spline_filter(mov.astype(float), order=5)
    I, J = np.meshgrid(np.arange(i - hi, i + hi + 1), np.arange(j - hj, j + hj + 1), indexing="ij")

    def neg(t):
        m = map_coordinates(coef, [I + t[0], J + t[1]], order=5, prefilter=False)
        return -float(np.sum(win * m)) / math.sqrt(float(np.sum(m * m)))

    best = min((neg([guess[0] + a, guess[1] + b]), (guess[0] + a, guess[1] + b))
               for a in range(-3, 4) for b in range(-1, 2))[1]
    res = minimize(neg, best, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-12})
    return res.x


def test_image_moves_by_the_true_displacement():
    # Registration convention: frames[0](x) ~ frames[k](x + u(x)), u from true_displacement in frame-0 coordinates.
    seq = small(n_frames=3, snr_db=None, depth_mm=30.0, width_mm=12.0, field=ShiftedField(0.25))
    dx, dy = seq.spacing
    k = 2
    errs = []
    for (xi, yj) in [(8.0, -2.0), (15.0, 1.5), (22.0, 0.0)]:
        i, j = int(round((xi - seq.origin[0]) / dx)), int(round((yj - seq.origin[1]) / dy))
        p = np.array([[seq.origin[0] + i * dx, seq.origin[1] + j * dy]])
        u = seq.true_displacement(k, p)[0] / np.array([dx, dy])
        est = _ncc_shift(seq.frames[0], seq.frames[k], i, j, 40, 8, np.round(u))
        errs.append(est - u)
    errs = np.array(errs)
    assert np.all(np.abs(u) > [5, 0.2]), f"test needs a sizeable motion, got {u} samples"
    assert np.abs(errs[:, 0]).max() < 0.1 and np.abs(errs[:, 1]).max() < 0.05, \
        f"estimated - true displacement (samples, [axial, lateral]): {errs}"


def test_frames_deterministic_for_a_seed():
    a, b, c = small(seed=3), small(seed=3), small(seed=4)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert not np.array_equal(a.frames[1], c.frames[1])


def test_sequence_snr_and_equal_noise_level():
    clean, noisy = small(snr_db=None), small(snr_db=12.0)
    for k in range(clean.n_frames):
        noise_var = float(np.mean((noisy.frames[k].astype(float) - clean.frames[k]) ** 2))
        ratio = noise_var / noisy.params["noise_sigma"] ** 2
        assert abs(ratio - 1) < 0.05, f"frame {k}: noise variance / sigma^2 = {ratio:.4f}"
    snr = measured_snr_db(clean.frames[0], noisy.frames[0])
    assert abs(snr - 12.0) < 0.5, f"measured SNR of frame 0: {snr:.3f} dB"


def test_inclusion_mask_and_doubled_amplitudes():
    seq = small(n_frames=1, snr_db=None, depth_mm=40.0, width_mm=20.0)
    dx, dy = seq.spacing
    area = seq.inclusion_mask.sum() * dx * dy
    assert abs(area / (math.pi * 7.5**2) - 1) < 0.02, f"mask area {area:.2f} mm^2"
    env2 = envelope(seq.frames[0]) ** 2
    X = seq.origin[0] + dx * np.arange(seq.shape[0])[:, None] + 0 * np.arange(seq.shape[1])
    Y = seq.origin[1] + dy * np.arange(seq.shape[1])[None, :] + 0 * X
    r = np.hypot(X - 30.0, Y)
    inner = env2[r < 6.0].mean()
    outer = env2[(r > 9.5) & (X > 2) & (X < 38) & (np.abs(Y) < 9)].mean()
    assert abs(inner / outer / 4 - 1) < 0.15, f"power ratio inside/outside {inner / outer:.3f} (amplitude x2 -> 4)"


def test_no_empty_margin_but_empty_band_above_the_moved_surface():
    seq = small(n_frames=20, snr_db=None, depth_mm=20.0, width_mm=8.0)
    env = envelope(seq.frames[-1].astype(float))
    x = seq.origin[0] + seq.spacing[0] * np.arange(seq.shape[0])
    u_top = seq.true_displacement(19, np.array([[0.0, 0.0]]))[0, 0]
    body = env[(x > u_top + 1) & (x < x[-1] - 1)]
    ref = np.sqrt(np.mean(body**2))
    bottom = np.sqrt(np.mean(env[x > x[-1] - 0.5] ** 2))
    sides = np.sqrt(np.mean(env[(x > u_top + 1)][:, [0, -1]] ** 2))
    assert bottom > 0.6 * ref and sides > 0.6 * ref, f"rms envelope bottom {bottom / ref:.2f}, sides {sides / ref:.2f}"
    # No tissue above the top face: the band the surface moved across is echo-free (module docstring).
    assert np.abs(seq.frames[-1][x < u_top - 1.0]).max() == 0.0


def test_true_fields_scale_linearly_and_reject_far_points():
    seq = small(n_frames=4)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 6, 50), rng.uniform(-2.5, 2.5, 50)])
    assert np.all(seq.true_displacement(0, pts) == 0)
    np.testing.assert_allclose(seq.true_strain(3, pts) * seq.scales[1], seq.true_strain(1, pts) * seq.scales[3],
                               rtol=1e-12, atol=1e-15)
    # bilinear interpolation of the 0.1 mm tables vs the analytic field itself
    ref = AnalyticField(40.0)
    err = np.abs(seq.true_displacement(2, pts) - seq.scales[2] * ref.displacement(pts)).max()
    assert err < 1e-6, f"max displacement interpolation error {err:.2e} mm"
    with pytest.raises(ValueError, match="outside"):
        seq.true_displacement(1, np.array([[50.0, 0.0]]))
    with pytest.raises(ValueError, match="frame index"):
        seq.true_strain(4, pts)


def test_analytic_field_strain_is_its_gradient():
    f = AnalyticField(5.0)
    assert np.isnan(f.displacement(np.array([[-0.01, 0.0]]))).all(), "NaN above the top face, like the FE field"
    p = np.array([[25.0, 3.0], [31.0, -2.0], [40.0, 0.5]])
    h = 1e-5
    gx = (f.displacement(p + [h, 0]) - f.displacement(p - [h, 0])) / (2 * h)
    gy = (f.displacement(p + [0, h]) - f.displacement(p - [0, h])) / (2 * h)
    fd = np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])
    np.testing.assert_allclose(f.strain(p), fd, atol=1e-9)


def test_save_and_load_identical(tmp_path):
    seq = small(n_frames=3)
    path = seq.save(tmp_path / "seq.npz")
    back = load_sequence(path)
    np.testing.assert_array_equal(back.frames, seq.frames)
    assert back.frames.dtype == np.float32
    assert back.spacing == seq.spacing and back.origin == seq.origin
    np.testing.assert_array_equal(back.inclusion_mask, seq.inclusion_mask)
    pts = np.column_stack([np.linspace(0.1, 5.9, 40), np.linspace(-2.4, 2.4, 40)])
    for k in range(3):
        np.testing.assert_array_equal(back.true_displacement(k, pts), seq.true_displacement(k, pts))
        np.testing.assert_array_equal(back.true_strain(k, pts), seq.true_strain(k, pts))
    assert back.params["seed"] == 0 and back.params["snr_db"] == 12.0
    assert back.params == {**seq.params}


def test_load_rejects_a_non_sequence_file(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.ones(3))
    with pytest.raises(ValueError, match="bad.npz"):
        load_sequence(bad)
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(ValueError, match="trunc.npz"):
        load_sequence(trunc)


@pytest.mark.parametrize("kwargs,name", [
    (dict(density_per_mm2=-30.0), "density"),
    (dict(density_per_mm2=0.0), "density"),
    (dict(snr_db=float("nan")), "snr_db"),
    (dict(snr_db=float("inf")), "snr_db"),
    (dict(spacing=(0.0, 0.3)), "spacing"),
    (dict(spacing=(0.02, -0.3)), "spacing"),
    (dict(model="2d"), "model"),
    (dict(inclusion="XX"), "inclusion"),
    (dict(n_frames=0), "n_frames"),
    (dict(seed=-1), "seed"),
])
def test_bad_input_raises_value_error_naming_it(kwargs, name):
    args = dict(model="3d", inclusion="HI", n_frames=2, seed=0, snr_db=12.0, depth_mm=2.0, width_mm=2.0,
                field=AnalyticField())
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        simulate_sequence(**args)


@pytest.fixture
def fake_fe(monkeypatch):
    calls = []

    def fe(model, inclusion_modulus, background_modulus, depth, diameter, options):
        calls.append(model)
        return AnalyticField(inclusion_modulus, background_modulus), "analytic-test"

    monkeypatch.setattr(S, "_fe_field", fe)
    return calls


def test_get_sequence_caches(tmp_path, fake_fe):
    a = forward.get_sequence("plane-stress", "SI", n_frames=2, depth_mm=3.0, width_mm=2.0, cache_dir=tmp_path)
    b = forward.get_sequence("plane-stress", "SI", n_frames=2, depth_mm=3.0, width_mm=2.0, cache_dir=tmp_path,
                             snr_db=12, psf=None)
    assert fake_fe == ["plane-stress"], "second call must load from the cache"
    assert a.path == b.path and a.path.parent == tmp_path
    np.testing.assert_array_equal(a.frames, b.frames)
    c = forward.get_sequence("plane-stress", "SI", n_frames=2, depth_mm=3.0, width_mm=2.0, cache_dir=tmp_path,
                             seed=1)
    assert c.path != a.path and len(fake_fe) == 2
    with pytest.raises(ValueError, match="nope"):
        forward.paper_datasets(["3d-HI", "nope"], cache_dir=tmp_path)


def test_cli_simulate(tmp_path, fake_fe, capsys):
    rc = main(["simulate", "--datasets", "3d-HOM,plane-strain-HI", "--cache-dir", str(tmp_path), "--n-frames", "3",
               "--depth-mm", "3", "--width-mm", "2", "--out", str(tmp_path / "out"), "--seed", "2"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "3d-HOM" in out and "plane-strain-HI" in out and "1->3" in out
    assert (tmp_path / "out" / "3d-HOM_seed2.npz").is_file()
    assert load_sequence(tmp_path / "out" / "plane-strain-HI_seed2.npz").params["seed"] == 2
    assert main(["simulate", "--datasets", "3d-XX", "--cache-dir", str(tmp_path)]) == 2
    assert main(["simulate", "--snr-db", "nan", "--cache-dir", str(tmp_path)]) == 2
    assert "snr" in capsys.readouterr().err


def test_fe_sequence_end_to_end(tmp_path, monkeypatch):
    # Real forward model (coarse plane-stress mesh, cached under tmp_path): the true fields are the FE solution
    # scaled per frame, and the image moves by them.
    monkeypatch.setenv("FEMREG_CACHE", str(tmp_path))
    from forward import cached_solve

    opts = {"mesh_size_mm": 2.0, "coarse_size_mm": 16.0}
    seq = simulate_sequence("plane-stress", "HI", n_frames=3, seed=1, snr_db=None, depth_mm=40.0, width_mm=12.0,
                            fe_options=opts)
    assert seq.params["field_source"].startswith("fe:")
    sol = cached_solve("plane-stress", inclusion_modulus=40.0, background_modulus=10.0, inclusion_depth_mm=30.0,
                       inclusion_diameter_mm=15.0, compression_mm=1.0, **opts)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(1, 39, 200), rng.uniform(-5.5, 5.5, 200)])
    u_fe = seq.scales[2] * sol.displacement(pts)
    err = np.abs(seq.true_displacement(2, pts) - u_fe).max() / np.abs(u_fe).max()
    assert err < 1e-3, f"true displacement vs FE solution: max relative difference {err:.2e}"
    e7 = seq.true_strain(2, seq.pixel_points())[:, 0]
    assert abs(-100 * e7.mean() - 0.2667) < 1e-3, f"mean compressive strain frame 3: {-100 * e7.mean():.4f} %"
    dx, dy = seq.spacing
    i, j = int(round(20.0 / dx)), int(round((2.0 - seq.origin[1]) / dy))
    p = np.array([[seq.origin[0] + i * dx, seq.origin[1] + j * dy]])
    u = seq.true_displacement(2, p)[0] / np.array([dx, dy])
    est = _ncc_shift(seq.frames[0], seq.frames[2], i, j, 40, 8, np.round(u))
    # Axial motion is ~16 samples here; the lateral one is tiny near the axis (the lateral direction is checked
    # with a lateral translation in test_image_moves_by_the_true_displacement), so only a loose bound laterally.
    assert np.all(np.abs(est - u) < [0.1, 0.1]), f"true {u}, image motion {est} (samples)"
