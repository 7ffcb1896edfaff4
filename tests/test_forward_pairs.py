"""forward.pairs / forward.fields: general probes, exact truth of simulated RF pairs, determinism."""
import numpy as np
import pytest

from forward import fields as F
from forward.pairs import PROBES, Probe, make_pair, make_sequence
from forward.ultrasound import envelope


def _fd_strain(field, pts, h=1e-4):
    gx = (field.displacement(pts + [h, 0]) - field.displacement(pts - [h, 0])) / (2 * h)
    gy = (field.displacement(pts + [0, h]) - field.displacement(pts - [0, h])) / (2 * h)
    return np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])


@pytest.mark.parametrize("name", ["paper", "L3", "L15"])
def test_integer_pixel_shift_moves_the_rf_exactly(name):
    pr = PROBES[name]
    dx, dy = pr.spacing
    p = make_pair(F.translation(7 * dx, 2 * dy), pr, (6.0, 6.0), snr_db=None, seed=1)
    ref, mov = p.ref, p.mov
    # mov(x + t) = ref(x): every interior sample reappears 7 samples deeper and 2 lines to the side.
    a, b = ref[:-7, :-2], mov[7:, 2:]
    assert np.max(np.abs(a - b)) < 1e-9 * np.sqrt(np.mean(ref**2))
    # ... and not by accident: the unshifted frames differ by about their own RMS.
    assert np.sqrt(np.mean((ref - mov) ** 2)) > 0.5 * np.sqrt(np.mean(ref**2))


def test_subsample_shift_matches_fourier_shift():
    pr = PROBES["paper"]
    dx = pr.spacing[0]
    p = make_pair(F.translation(0.37 * dx, 0.0), pr, (10.0, 3.0), snr_db=None, seed=2)
    n = p.ref.shape[0]
    k = np.fft.rfftfreq(n)
    shifted = np.fft.irfft(np.fft.rfft(p.ref, axis=0) * np.exp(-2j * np.pi * k * 0.37)[:, None], n=n, axis=0)
    inner = slice(100, n - 100)   # away from the periodic wrap of the FFT
    err = np.sqrt(np.mean((shifted[inner] - p.mov[inner]) ** 2) / np.mean(p.mov[inner] ** 2))
    assert err < 1e-3   # measured 6.6e-4: the PSF truncated at 4 sigma (4e-4 per factor), not band-limited


@pytest.mark.parametrize("field", [F.compression(0.03), F.shear_rotation(0.01), F.Bending(0.002, 0.02, 30.0),
                                   F.translation(0.5, -0.2)])
def test_analytic_strain_is_the_gradient_of_the_displacement(field):
    rng = np.random.default_rng(0)
    pts = rng.uniform([1.0, -20.0], [60.0, 20.0], (200, 2))
    np.testing.assert_allclose(field.strain(pts), _fd_strain(field, pts), atol=1e-8)


def test_analytic_fields_have_their_stated_strain():
    s = 0.05
    c = F.compression(s)
    assert np.linalg.det(np.eye(2) + c.G) == pytest.approx(1.0, abs=1e-12)   # area preserved
    assert c.strain(np.zeros((1, 2)))[0, 0] == pytest.approx(-s)
    sr = F.shear_rotation(0.01, shear=0.006, rotation_deg=0.1)
    e = sr.strain(np.zeros((1, 2)))[0]
    assert e[2] == pytest.approx(0.003, abs=2e-5)   # rotation changes e_xy by O(theta * s) ~ 1e-5
    b = F.Bending(0.002, 0.02, width_mm=40.0)
    exx = b.strain(np.array([[10.0, -20.0], [10.0, 20.0]]))[:, 0]
    np.testing.assert_allclose(exx, [-0.002, -0.02])
    assert np.all(b.at(0.0).displacement(np.ones((3, 2))) == 0)
    np.testing.assert_allclose(F.compression(0.01).at(0.03).G, F.compression(0.03).G)


def test_pair_is_deterministic_per_seed():
    args = (F.compression(0.02), "L7", (8.0, 6.0), 20.0)
    a, b, c = make_pair(*args, seed=3), make_pair(*args, seed=3), make_pair(*args, seed=4)
    assert np.array_equal(a.ref, b.ref) and np.array_equal(a.mov, b.mov)
    assert not np.allclose(a.ref, c.ref)


@pytest.mark.parametrize("name", list(PROBES))
def test_every_probe_gives_fully_developed_speckle(name):
    pr = PROBES[name]
    p = make_pair(F.compression(0.0), pr, (10.0, 10.0), snr_db=None, seed=0)
    assert p.ref.shape == (round(10.0 / pr.spacing[0]), round(10.0 / pr.spacing[1]))
    env = envelope(p.ref)
    # Rayleigh speckle: mean / std = 1.91; measured 1.84-1.88 on 15-80 mm images of the five presets.
    assert 1.7 < env.mean() / env.std() < 2.0


def test_noise_level_follows_snr():
    p0 = make_pair(F.compression(0.01), "paper", (10.0, 6.0), snr_db=None, seed=5)
    p1 = make_pair(F.compression(0.01), "paper", (10.0, 6.0), snr_db=10.0, seed=5)
    snr = 10 * np.log10(np.mean(p0.ref**2) / np.mean((p1.ref - p0.ref) ** 2))
    assert snr == pytest.approx(10.0, abs=0.2)   # 16 k noise samples: +-0.05 dB (1 sigma)


def test_sequence_frames_follow_the_field_levels():
    pr = PROBES["paper"]
    dx = pr.spacing[0]
    base = F.Affine(np.zeros((2, 2)), shift=(10 * dx, 0.0), level=0.01)
    seq = make_sequence(base, pr, (6.0, 3.0), snr_db=None, seed=0, n_frames=4, step=0.01)
    assert seq.frames.shape[0] == 4
    np.testing.assert_allclose(seq.levels, [0, 0.01, 0.02, 0.03])
    pts = np.array([[3.0, 0.0]])
    np.testing.assert_allclose(seq.true_displacement(2, pts), [[20 * dx, 0.0]])
    f0, f2 = seq.frames[0], seq.frames[2]
    assert np.max(np.abs(f0[:-20] - f2[20:])) < 1e-9 * np.sqrt(np.mean(f0**2))


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="twice the centre frequency"):
        Probe(10.0, 15.0, 0.2, 1.0)
    with pytest.raises(ValueError, match="unknown probe preset"):
        make_pair(F.compression(0.01), "L99")
    with pytest.raises(ValueError, match="size_mm"):
        make_pair(F.compression(0.01), "paper", (0.0, 10.0))
    with pytest.raises(ValueError, match="strain level"):
        F.compression(0.7)
    with pytest.raises(ValueError, match="seed"):
        make_pair(F.compression(0.01), "paper", (5.0, 5.0), seed=-1)


def test_plain_callable_field():
    p = make_pair(lambda q: np.column_stack([0.01 * q[:, 1], np.zeros(len(q))]), "paper", (5.0, 5.0), seed=0)
    e = p.true_strain(np.array([[3.0, 1.0]]))
    np.testing.assert_allclose(e, [[0.0, 0.0, 0.005]], atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["plane-strain", "plane-stress"])
def test_fe_inclusion_field(model):
    f = F.Inclusion("stiff", model, 0.04)
    rng = np.random.default_rng(0)
    pts = rng.uniform([3.0, -12.0], [40.0, 12.0], (300, 2))
    pts = pts[np.abs(np.hypot(pts[:, 0] - 20.0, pts[:, 1]) - 5.0) > 0.5]   # away from the material interface
    np.testing.assert_allclose(f.strain(pts), _fd_strain(f, pts, 1e-5), atol=1e-8)   # measured 1.2e-10
    # the probe face does not move axially; a stiff inclusion strains less than the background
    assert np.max(np.abs(f.displacement(np.array([[0.0, y] for y in np.linspace(-10, 10, 5)]))[:, 0])) < 1e-9
    e_in = f.strain(np.array([[20.0, 0.0]]))[0, 0]
    e_out = f.strain(np.array([[20.0, 12.0]]))[0, 0]
    assert abs(e_in) < 0.6 * abs(e_out)
