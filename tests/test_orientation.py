"""Orientation and sampling check (femreg.orientation): transposed frames and swapped spacing are input errors
named as such; correct RF, envelopes and smooth images pass.  The thresholds' margins are those measured in the
module docstring (benchmarks/orientation_check.py runs the whole test set)."""
from pathlib import Path

import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.orientation import (CARRIER_RATIO, ENVELOPE_CELL_MM, MIN_LATERAL_CELL_PERIODS, NO_CARRIER_RATIO,
                                OrientationError,
                                carrier_ratio, check, diagnose, transposed_message)
from femreg.pyramid import envelope

INVIVO = Path(__file__).resolve().parents[2] / "shared" / "data" / "invivo_rf"


@pytest.fixture(scope="module")
def probes():
    from forward import fields as F
    from forward.pairs import PROBES, make_pair

    return {name: make_pair(F.compression(0.01), PROBES[name], (15, 10), 20, seed=3) for name in ("L3", "L7", "L15")}


def _invivo(seq):
    path = INVIVO / seq / "frame1.raw"
    if not path.is_file():
        pytest.skip("in vivo data not available")
    return np.fromfile(path, "<f4").reshape(2000, 128)


def test_simulated_probes_pass_and_their_mistakes_are_refused(probes):
    for name, p in probes.items():
        sp = tuple(p.spacing)
        ok = check(p.ref, sp)
        f0 = p.probe.f0_mhz
        assert abs(ok.frequency_mhz - f0) < 0.1 * f0, (name, ok)          # the carrier is the probe's
        assert ok.cell_periods > 3 * MIN_LATERAL_CELL_PERIODS, (name, ok)
        assert diagnose(envelope(p.ref), sp).problem == ""                 # no carrier: never refused
        with pytest.raises(OrientationError, match="transposed") as e:
            check(p.ref.T, sp[::-1])
        assert "--no-orientation-check" in str(e.value) and "check_orientation=False" in str(e.value)
        with pytest.raises(OrientationError, match="swapped") as e:
            check(p.ref, sp[::-1])
        assert f"({sp[0]:g}, {sp[1]:g})" in str(e.value)                  # names the spacing to pass
        assert f"CLI: --spacing {sp[0]:g} {sp[1]:g}" in str(e.value)        # and the flag that passes it


def test_transposed_refusal_words_a_range_step(probes):
    """A convex / sector frame's spacing is the range step alone (its lateral value is the rays' distance at the
    middle sample): the refusal's report words it so, ``--spacing DR auto``, with no lateral value to keep,
    exchange or rescale; a linear frame's wording is the one the check raised."""
    from femreg.errors import cli_wording

    p = probes["L7"]
    dx, dy = (float(v) for v in p.spacing)
    with pytest.raises(OrientationError, match="transposed") as e:
        check(p.ref.T, (dx, dy))
    rep = e.value.report
    assert rep.problem == "transposed" and transposed_message(rep) == str(e.value)
    beam = transposed_message(rep, range_step=True)
    assert f"keep the spacing {dx:g} mm (range step; " in beam and f"CLI: --spacing {dx:g} auto)" in beam, beam
    assert f"{dy:g}" not in beam, beam
    with cli_wording():
        assert f"keep --spacing {dx:g} auto (range step; " in transposed_message(rep, range_step=True)
        metres = transposed_message(diagnose(p.ref.T, (dx * 1e-3, dy * 1e-3)), range_step=True)
    assert f"units look like metres), --spacing {dx:g} auto (range step; " in metres, metres
    # ten times the range step: 7.5 MHz read as 0.75, no unit explains it
    far = transposed_message(diagnose(p.ref.T, (dx * 10, dy)), range_step=True)
    assert f"check the range step (the axial spacing, mm): {dx * 10:g} mm gives" in far, far


@pytest.mark.parametrize("seq", ["seq299", "seq304"])
def test_invivo_frames_pass_transposed_and_swapped_are_refused(seq):
    rf = _invivo(seq)
    rep = check(rf, (0.02, 0.2))
    assert 3.5 < rep.frequency_mhz < 5.5            # README of the data: about 4 MHz dominant frequency
    assert rep.carrier[0] < CARRIER_RATIO / 5 and rep.carrier[1] > NO_CARRIER_RATIO * 4
    assert diagnose(rf.T, (0.2, 0.02)).problem == "transposed"
    # the advice names the spacing to pass after transposing, whichever order the user gave it in
    for given in ((0.02, 0.2), (0.2, 0.02)):
        msg = diagnose(rf.T, given).message
        assert "CLI: --spacing 0.02 0.2" in msg and "4." in msg, msg
    assert "keep the spacing (0.02, 0.2)" in diagnose(rf.T, (0.02, 0.2)).message
    assert diagnose(rf, (0.2, 0.02)).problem == "swapped"
    assert diagnose(envelope(rf), (0.02, 0.2)).problem == ""
    assert diagnose(20 * np.log10(envelope(rf) + 1e-3), (0.02, 0.2)).problem == ""   # log-compressed B-mode


def test_spacing_in_wrong_units_is_refused(probes):
    p = probes["L7"]
    sp = np.asarray(p.spacing) * 1000.0            # micrometres given as mm
    rep = diagnose(p.ref, sp)
    assert rep.problem == "spacing" and "units" in rep.message and rep.frequency_mhz < 0.01
    # the advice names the unit and the spacing in mm, for micrometres and for metres (the common slips)
    mm = ", ".join(f"{v:.6g}" for v in p.spacing)
    assert "units look like micrometres" in rep.message and f"({mm})" in rep.message, rep.message
    rep = diagnose(p.ref, np.asarray(p.spacing) / 1000.0)
    assert rep.problem == "spacing" and "units look like metres" in rep.message and f"({mm})" in rep.message
    # a volume's advice scales its elevational spacing too
    rep = diagnose(p.ref, np.asarray(p.spacing) / 1000.0, elevational=0.5e-3)
    assert f"({mm}, 0.5)" in rep.message, rep.message


def test_images_without_carrier_pass():
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.linspace(0, 1, 120), np.linspace(0, 1, 60), indexing="ij")
    smooth = np.exp(-((x - 0.5) ** 2 + (y - 0.4) ** 2) / 0.05)
    lateral_stripes = np.sin(2 * np.pi * 12 * y) + 0.0 * x       # constant along axis 0: nothing to measure there
    noise = rng.standard_normal((120, 60))
    for img in (smooth, lateral_stripes, noise, rng.standard_normal((8, 6))):
        assert diagnose(img, (0.02, 0.2)).problem == ""
    assert carrier_ratio(noise) > NO_CARRIER_RATIO                # white noise is no carrier


def test_register_and_track_refuse_before_any_work(probes, tmp_path):
    p = probes["L7"]
    sp = tuple(p.spacing)
    with pytest.raises(OrientationError, match="transposed"):
        femreg.register(p.ref.T, p.mov.T, spacing=sp[::-1])
    with pytest.raises(InputError, match="swapped"):
        femreg.register(p.ref, p.mov, spacing=sp[::-1], alpha="auto")
    with pytest.raises(OrientationError, match="swapped"):
        femreg.track(np.stack([p.ref, p.mov]), spacing=sp[::-1], checkpoint_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()                        # refused before the folder was made
    res = femreg.register(p.ref, p.mov, spacing=sp[::-1], check_orientation=False, maxiter=2, margin=0.1)
    assert res.mesh.p.shape[1] > 0                                # the override runs the registration


def _bmode(rf):
    env = envelope(rf)
    return 20 * np.log10(env / env.max() + 1e-6)            # log-compressed, as scanners display it


def test_envelope_and_bmode_spacing_mistakes_are_refused(probes):
    """Without a carrier the speckle cells are the spacing's witness: on the L3-L15 envelopes and B-modes the
    correct spacing passes, exchanged spacings are named as swapped and metres as metres (benchmarks/
    orientation_check.py: 0 false alarms, every non-square exchange found)."""
    for name, p in probes.items():
        sp = tuple(p.spacing)
        for img in (envelope(p.ref), _bmode(p.ref)):
            ok = diagnose(img, sp)
            assert ok.problem == "" and "a plausible spacing" in ok.summary(), (name, ok)
            a0, l0 = ENVELOPE_CELL_MM[0][0], ENVELOPE_CELL_MM[1][0]
            # the measured cells clear the lower bounds by at least the 1.5x the module's margin claims
            assert ok.axial_cell_mm > 1.5 * a0 and ok.lateral_cell_mm > 1.5 * l0, (name, ok)
            sw = diagnose(img, sp[::-1])
            assert sw.problem == "swapped", (name, sw)
            assert f"--spacing {sp[0]:g} {sp[1]:g}" in sw.message, sw.message
            m = diagnose(img, tuple(v / 1000.0 for v in sp))
            assert m.problem == "spacing" and "units look like metres" in m.message, (name, m.message)


def test_scan_converted_bmode_in_centimetres_is_refused(probes):
    """A clinic's scan-converted B-mode (square 0.1 mm pixels) whose header's 0.01 cm is typed as mm: the cells
    come out 10 x too small for any probe, and the advice gives the spacing in mm."""
    from scipy.ndimage import zoom

    p = probes["L15"]
    dx, dy = p.spacing
    frames = [zoom(_bmode(f), (dx / 0.1, dy / 0.1), order=1) for f in (p.ref, p.mov)]
    assert diagnose(frames[0], (0.1, 0.1)).problem == ""
    rep = diagnose(frames[0], (0.01, 0.01))
    assert rep.problem == "spacing" and "units look like centimetres" in rep.message, rep.message
    assert "CLI: --spacing 0.1 0.1" in rep.message, rep.message
    with pytest.raises(OrientationError, match="centimetres"):
        femreg.track(np.stack(frames), spacing=(0.01, 0.01))
