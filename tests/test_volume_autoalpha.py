"""alpha="auto" on volumes (femreg.autoalpha with femreg.volume's registration and image term): the choice follows
the noise level, is recorded in the result and its file, and works through track and the CLI."""
import numpy as np
import pytest

import femreg
from femreg.errors import FileFormatError, InputError
from femreg.volume_result import load_volume_result

from _volumes import volume_pair

SHAPE, SPACING = (240, 30, 24), (0.025, 0.2, 0.25)       # 6 x 6 x 6 mm at 7 MHz
CENTRE = np.array(SHAPE) * np.array(SPACING) / 2
KW = dict(spacing=SPACING, element_size=1.0)


def _field(X):
    # 1 % compression with a Gaussian bump (1.5 mm): strain contrast the default regulariser's null space lacks
    d = np.asarray(X, float) - CENTRE
    b = np.exp(-0.5 * np.sum(d ** 2, axis=1) / 1.5 ** 2)
    return np.column_stack([-0.01 * d[:, 0] + 0.015 * b, 0.005 * d[:, 1] + 0.01 * b * d[:, 1] / 1.5,
                            0.005 * d[:, 2]])


@pytest.fixture(scope="module")
def pairs():
    return {snr: volume_pair(_field, shape=SHAPE, spacing=SPACING, f_mhz=7.0, seed=0, snr_db=snr)[:2]
            for snr in (40.0, 0.0)}


@pytest.fixture(scope="module")
def auto_results(pairs):
    return {snr: femreg.register(ref, mov, alpha="auto", **KW) for snr, (ref, mov) in pairs.items()}


def test_auto_alpha_regularises_noisy_volumes_more(auto_results):
    low, high = auto_results[40.0], auto_results[0.0]
    # measured: 0.0133 at 40 dB SNR, 0.0422 at 0 dB (the default alpha 0.133); the grid 0.0042 ... 4.2
    assert low.auto_alpha.alpha < high.auto_alpha.alpha, (low.auto_alpha, high.auto_alpha)
    for r in (low, high):
        ch = r.auto_alpha
        assert r.success and r.alpha == pytest.approx(ch.alpha)
        assert ch.rule == "quasi-optimality" and ch.n_registrations == 7 and ch.n_successful == 7
        assert ch.alphas.shape == ch.psi.shape == ch.dof.shape == (7,) and ch.strain_change.shape == (6,)
        assert np.all(np.diff(ch.dof) < 0)              # more regularisation, fewer fitted degrees of freedom
        assert ch.alpha in ch.alphas[1:-1]              # an interior candidate (the rule never takes an end)
    # the noise of the pair shows in the change of the strains at the smallest alphas (measured 0.005 vs 0.039)
    assert high.auto_alpha.strain_change[0] > 3 * low.auto_alpha.strain_change[0]


def test_auto_alpha_is_saved_with_the_volume_result(auto_results, tmp_path):
    r = auto_results[0.0]
    back = femreg.load_result(r.save(tmp_path / "v.npz"))
    a, b = r.auto_alpha, back.auto_alpha
    assert b is not None and b.alpha == a.alpha and b.rule == a.rule and b.n_successful == a.n_successful
    for k in ("alphas", "psi", "dof", "upre", "strain_change"):
        np.testing.assert_array_equal(getattr(b, k), getattr(a, k))
    # a plain result has no record, and a file whose record is not one is refused naming the entry
    plain = femreg.register(*volume_pair(_field, shape=SHAPE, spacing=SPACING, seed=1)[:2], alpha=0.1, **KW)
    assert load_volume_result(plain.save(tmp_path / "p.npz")).auto_alpha is None
    with np.load(tmp_path / "v.npz") as z:
        d = dict(z)
    d["auto_alpha"] = np.array("{not json")
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(FileFormatError, match="auto_alpha"):
        load_volume_result(tmp_path / "bad.npz")


def test_auto_alpha_is_saved_with_a_2d_result(auto_results, tmp_path):
    from femreg.mesh import roi_mesh

    mesh = roi_mesh((100, 40), (0.05, 0.3), element_size=1.0)
    u = np.random.default_rng(0).normal(0.0, 0.01, 2 * mesh.p.shape[1])
    res = femreg.RegistrationResult(mesh, u, shape=(100, 40), spacing=(0.05, 0.3), origin=(0.0, 0.0), alpha=0.0133)
    res.auto_alpha = auto_results[40.0].auto_alpha       # the record is the same class in 2D and 3D
    back = femreg.load_result(res.save(tmp_path / "f.npz"))
    assert back.auto_alpha.alpha == res.auto_alpha.alpha
    np.testing.assert_array_equal(back.auto_alpha.strain_change, res.auto_alpha.strain_change)
    res.auto_alpha = None
    assert femreg.load_result(res.save(tmp_path / "g.npz")).auto_alpha is None


def test_track_chooses_alpha_on_the_first_pair(pairs):
    ref, mov = pairs[40.0]
    third = volume_pair(lambda X: 1.5 * _field(X), shape=SHAPE, spacing=SPACING, f_mhz=7.0, seed=0,
                        snr_db=40.0)[1]
    # a 4 x 4 x 4 mm piece: the choice made once and shared does not depend on the size
    tr = femreg.track([v[:160, 5:25, 4:20] for v in (ref, mov, third)], alpha="auto", **KW)
    ch = tr.results[0].auto_alpha
    assert ch is not None and ch.n_registrations == 7
    assert all(r.auto_alpha is ch and r.alpha == pytest.approx(ch.alpha) for r in tr.results + tr.accumulated)
    with pytest.raises(InputError, match="auto"):
        femreg.track([ref, mov], alpha="automatic", **KW)


def test_cli_register_alpha_auto_on_volumes(pairs, tmp_path, capsys):
    from femreg.cli import main

    # a 4 x 4 x 4 mm piece: what is checked (the choice recorded, exit codes) does not depend on the size
    ref, mov = (v[:160, 5:25, 4:20] for v in pairs[40.0])
    seq = tmp_path / "seq.npz"
    np.savez(seq, rf=np.stack([ref, mov]), spacing=np.asarray(SPACING))
    out = tmp_path / "r.npz"
    assert main(["register", str(seq), "-o", str(out), "--alpha", "auto", "--element-size", "1"]) == 0
    res = load_volume_result(out)
    assert res.auto_alpha is not None and res.alpha == pytest.approx(res.auto_alpha.alpha)
    assert main(["track", str(seq), "-o", str(tmp_path / "t"), "--alpha", "auto", "--element-size", "1"]) == 0
    tracked = load_volume_result(tmp_path / "t" / "frame_001.npz")
    assert tracked.auto_alpha is not None and tracked.alpha == pytest.approx(tracked.auto_alpha.alpha)
    capsys.readouterr()
    # bad input: exit 2 with the reason, before any candidate is registered
    other = tmp_path / "other.npz"
    np.savez(other, rf=mov[:-10], spacing=np.asarray(SPACING))
    assert main(["register", str(seq), str(other), "-o", str(out), "--alpha", "auto"]) == 2
    assert "shape" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["register", str(seq), "-o", str(out), "--alpha", "sometimes"])
    assert exc.value.code == 2
    with pytest.raises(InputError, match="auto"):
        femreg.register(ref, mov, alpha="automatic", **KW)
