"""The axial spacing held against what the file and the RF say about it (femreg.orientation.check_sampling,
frequency_note): a spacing that disagrees with the header's sampling rate c / (2 fs), or that puts the RF carrier
far from the header's transmit frequency, is refused naming both values; milder mismatches and a carrier outside
clinical probes' band are noted.  Margins are those measured by benchmarks/spacing_check.py (carrier / centre
frequency 0.977-1.077 on the simulated 3-15 MHz probes; in vivo 4.52-4.65 MHz)."""
import re
from pathlib import Path

import numpy as np
import pytest

import femreg
from femreg.cli import main
from femreg.io import read_frames
from femreg.io.checks import header_frequencies
from femreg.io.frames import Frames
from femreg.io.ultrasonix import write_ultrasonix
from femreg.orientation import (FREQUENCY_MHZ, TRANSMIT_NOTE_RATIO, TRANSMIT_RATIO, TYPICAL_MHZ, OrientationError,
                                carrier_frequency, check_sampling, frequency_note)

INVIVO = Path(__file__).resolve().parents[2] / "shared" / "data" / "invivo_rf"
C = 1540.0


@pytest.fixture(scope="module")
def pairs():
    from forward import fields as F
    from forward.pairs import PROBES, make_pair

    return {name: make_pair(F.compression(0.01), PROBES[name], (12, 8), 20, seed=5) for name in ("L3", "paper", "L15")}


def _counts(p):
    frames = np.stack([p.ref, p.mov])
    return frames / np.abs(frames).max() * 20000


@pytest.fixture(scope="module")
def rf_files(pairs, tmp_path_factory):
    """An Ultrasonix file per probe: sf its sampling rate, txf its centre frequency."""
    d = tmp_path_factory.mktemp("sampling")
    out = {}
    for name, p in pairs.items():
        out[name] = write_ultrasonix(d / f"{name}.rf", _counts(p), p.spacing,
                                     header={"txf": int(p.probe.f0_mhz * 1e6)})[0]
    return out


def test_header_frequencies_are_read_from_ultrasonix_and_settings_fields(rf_files):
    fr = read_frames(rf_files["paper"], spacing=(None, 0.3))
    known = header_frequencies(fr.metadata)
    assert known["fs_mhz"][0] == pytest.approx(40.0) and known["transmit_mhz"][0] == pytest.approx(5.5)
    assert "sf" in known["fs_mhz"][1] and "txf" in known["transmit_mhz"][1]
    # a Clarius settings file's words, a sidecar's Hz: units from the name or the magnitude
    clarius = header_frequencies({"fields": {"sampling rate_MHz": 60.0, "transmit frequency_MHz": 10.0}})
    assert clarius["fs_mhz"][0] == 60.0 and clarius["transmit_mhz"][0] == 10.0
    side = header_frequencies({"fields": {"fs": 4e7, "center_frequency": 7.5e6, "c": 1480.0}})
    assert side["fs_mhz"][0] == 40.0 and side["transmit_mhz"][0] == 7.5 and side["sound_speed"][0] == 1480.0
    assert header_frequencies({"fields": {"fs": 2e9}}) == {}             # 2000 MHz: no ultrasound setting


def test_correct_spacing_passes_and_every_common_mistake_is_refused(pairs, rf_files):
    for name, p in pairs.items():
        dx, dy = p.spacing
        for sp in ((dx, dy), (None, dy), (dx * 1.04, dy)):               # 4 %: a speed of sound of 1600 m/s
            fr = read_frames(rf_files[name], spacing=sp)
            assert not fr.metadata.get("sampling_notes"), (name, sp, fr.metadata.get("sampling_notes"))
        for k, said in ((2.0, "factor 2 of the two-way travel"), (0.5, "twice the sampling rate"),
                        (2.7, "2.7 times"), (1 / 2.7, "0.37 times"), (10.0, "decade"), (0.1, "centimetres"),
                        (1000.0, "micrometres")):
            with pytest.raises(OrientationError) as e:
                read_frames(rf_files[name], spacing=(dx * k, dy))
            msg = str(e.value)
            assert e.value.problem == "sampling" and said in msg, (name, k, msg)
            assert f"states {p.probe.fs_mhz:g} MHz" in msg and f"c / (2 fs) is {dx:.5g} mm" in msg, msg
            assert f"({dx:.5g}, {dy:g})" in msg and "check_orientation=False" in msg, msg   # the fix, the way out
        fr = read_frames(rf_files[name], spacing=(dx * 2, dy), check_orientation=False)      # overridden
        assert fr.spacing[0] == pytest.approx(2 * dx)


def test_a_swapped_spacing_is_left_to_the_orientation_checks(pairs, rf_files):
    p = pairs["paper"]
    dx, dy = p.spacing
    fr = read_frames(rf_files["paper"], spacing=(dy, dx))                # exchanged: not a sampling mistake
    with pytest.raises(OrientationError) as e:
        femreg.register(fr.frames[0], fr.frames[1], spacing=fr.spacing)
    assert e.value.problem == "swapped"


def test_a_wrong_header_rate_is_caught_by_the_transmit_frequency(pairs, tmp_path):
    """The spacing taken from a header whose sf is wrong: the carrier against txf.  Half the rate (spacing 2 x)
    reads 0.49-0.54 of txf, noted; a quarter (4 x) refused."""
    p = pairs["paper"]
    fs, f0 = p.probe.fs_mhz * 1e6, p.probe.f0_mhz * 1e6
    for k, refused in ((0.5, False), (2.0, False), (0.25, True), (4.0, True)):
        path = write_ultrasonix(tmp_path / f"k{k:g}.rf", _counts(p), sampling_frequency=fs * k,
                                header={"txf": int(f0)})[0]
        if refused:
            with pytest.raises(OrientationError, match=r"times the transmit frequency the file states, 5\.5 MHz"):
                read_frames(path, spacing=(None, 0.3))
            continue
        notes = read_frames(path, spacing=(None, 0.3)).metadata["sampling_notes"]
        assert len(notes) == 1 and f"{k:.2f} times the transmit frequency" in notes[0], notes
        assert ("harmonic" in notes[0]) == (k > 1), notes                # twice the transmit: harmonic imaging
        # the spacing that would put the carrier at txf is the true one, within the carrier's 0.977-1.077
        cure = float(re.search(r"an axial spacing of ([0-9.]+) mm would put the carrier at 5\.5 MHz", notes[0])[1])
        assert cure == pytest.approx(p.spacing[0], rel=0.1), notes


def test_decimated_frames_take_the_spacing_given_when_the_carrier_agrees(pairs, tmp_path):
    """Every second sample kept, the header's sf the rate before: the spacing given (2 c / (2 fs)) puts the
    carrier at txf, so it is used with a note; without txf it is refused, naming decimation."""
    p = pairs["paper"]
    dx, dy = p.spacing
    dec = _counts(p)[:, ::2]
    with_tx = write_ultrasonix(tmp_path / "dec.rf", dec, sampling_frequency=40e6, header={"txf": 5_500_000})[0]
    fr = read_frames(with_tx, spacing=(2 * dx, dy))
    assert fr.spacing[0] == pytest.approx(2 * dx)
    assert "one before decimation" in fr.metadata["sampling_notes"][0]
    bare = write_ultrasonix(tmp_path / "bare.rf", dec, sampling_frequency=40e6)[0]
    with pytest.raises(OrientationError, match=r"one sample in 2 kept"):
        read_frames(bare, spacing=(2 * dx, dy))


def test_transmit_bounds_have_room_for_measured_carriers_and_harmonics(pairs):
    for name, p in pairs.items():
        r = carrier_frequency(p.ref, p.spacing[0]) / p.probe.f0_mhz
        assert 0.95 < r < 1.1, (name, r)                                  # measured 0.977-1.077
        assert TRANSMIT_NOTE_RATIO[0] < r / 1.3 and r * 1.3 < TRANSMIT_NOTE_RATIO[1]   # 30 % for a downshift
        assert TRANSMIT_RATIO[0] > r / 2.7 and r * 2.7 > TRANSMIT_RATIO[1]   # 2.7 x either way: refused
    assert TRANSMIT_RATIO[1] > 2.0 * 1.15                                # harmonic imaging, 15 % up: noted only


def test_iq_and_envelope_frames_skip_the_carrier_checks(pairs):
    from femreg.pyramid import envelope

    p = pairs["paper"]
    meta = {"fields": {"fs_MHz": 40.0, "f0_MHz": 5.5}}
    env = Frames(frames=envelope(p.ref)[None], spacing=p.spacing, metadata=meta, source=Path("env.npz"))
    assert check_sampling(env) == []                                     # no carrier: nothing to compare
    with pytest.raises(OrientationError, match="file states 40 MHz"):   # the rate still holds for its samples
        check_sampling(env, (2 * p.spacing[0], p.spacing[1]))
    iq = Frames(frames=p.ref[None], spacing=p.spacing, metadata=dict(meta, iq={"modulation_frequency_mhz": 5.5}),
                source=Path("iq.npz"))
    assert check_sampling(iq, (2 * p.spacing[0], p.spacing[1])) == []   # the carrier is the demodulation's


def test_frequency_note_band():
    lo, hi = TYPICAL_MHZ
    assert frequency_note(4.6) == "" and frequency_note(lo * 1.01) == "" and frequency_note(hi * 0.99) == ""
    assert frequency_note(FREQUENCY_MHZ[0] / 2) == ""                    # refused by diagnose, not noted
    assert "too large" in frequency_note(1.1) and "1.1 MHz" in frequency_note(1.1)
    assert "too small" in frequency_note(40.0) and "preclinical" in frequency_note(40.0)


def test_register_notes_a_carrier_outside_clinical_probes(pairs):
    """L15 with its spacing 2.7 x too small reads 40 MHz (passes diagnose's 1-60 MHz): noted; as given, not."""
    p = pairs["L15"]
    dx, dy = p.spacing
    ok = femreg.register(p.ref, p.mov, spacing=(dx, dy), maxiter=3)
    assert "clinical probes" not in ok.message
    off = femreg.register(p.ref, p.mov, spacing=(dx / 2.7, dy), maxiter=3)
    assert "outside the 2-20 MHz of clinical probes" in off.message and "too small" in off.message, off.message


@pytest.mark.parametrize("seq", ["seq299", "seq304"])
def test_invivo_frames_no_false_alarm(seq, tmp_path):
    path = INVIVO / seq / "frame1.raw"
    if not path.is_file():
        pytest.skip("in vivo data not available")
    a = np.fromfile(path, "<f4").reshape(2000, 128)
    f = carrier_frequency(a, 0.02)
    assert 4.0 < f < 5.2 and frequency_note(f) == ""                     # measured 4.52-4.56 MHz
    assert "too large" in frequency_note(carrier_frequency(a, 0.02 * 2.7))       # 1.7 MHz
    # written with the sampling rate 0.02 mm implies and a 4.5 MHz transmit: passes as given, 2 x refused
    p = write_ultrasonix(tmp_path / "v.rf", np.stack([a, a]) * 20000, (0.02, 0.2), header={"txf": 4_500_000})[0]
    assert not read_frames(p, spacing=(0.02, 0.2)).metadata.get("sampling_notes")
    with pytest.raises(OrientationError, match="factor 2 of the two-way travel"):
        read_frames(p, spacing=(0.04, 0.2))


def test_cli_refuses_with_exit_2_and_info_names_it(rf_files, pairs, tmp_path, capsys):
    p = pairs["paper"]
    dx, dy = p.spacing
    rc = main(["register", str(rf_files["paper"]), "-o", str(tmp_path / "r.npz"), "--spacing", "0.0385", str(dy),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "implies 20 MHz sampling" in err and "states 40 MHz" in err, err
    assert f"--spacing {dx:.5g} {dy:g}" in err and "--no-orientation-check" in err and "Traceback" not in err
    rc = main(["info", str(rf_files["paper"]), "--spacing", "0.0385", str(dy)])
    out = capsys.readouterr().out
    assert rc == 1 and "implies 20 MHz sampling" in out, out
    rc = main(["info", str(rf_files["paper"]), "--spacing", "auto", str(dy)])
    assert rc == 0, capsys.readouterr().out


def test_track_says_the_carrier_note_once(pairs, tmp_path, capsys):
    """track prints no pair's message: the band note comes on stderr from the frames as read; register prints it
    as a note line."""
    p = pairs["L15"]
    dx, dy = p.spacing
    np.save(tmp_path / "l15.npy", np.stack([p.ref, p.mov]).astype("f4"))
    for k, noted in ((1.0, False), (1 / 2.7, True)):
        rc = main(["track", str(tmp_path / "l15.npy"), "--spacing", f"{dx * k:.6g}", str(dy), "-o",
                   str(tmp_path / f"t{k:.2f}"), "--no-progress", "--maxiter", "3"])
        err = capsys.readouterr().err
        assert rc == 0 and ("outside the 2-20 MHz of clinical probes" in err) == noted, err
        # register prints it as a note line of its own, not only inside the pair's message
        rc = main(["register", str(tmp_path / "l15.npy"), "--spacing", f"{dx * k:.6g}", str(dy), "-o",
                   str(tmp_path / f"r{k:.2f}.npz"), "--no-progress", "--maxiter", "3"])
        out = capsys.readouterr().out
        assert rc == 0 and ("femreg register: note: the RF carrier reads" in out) == noted, out


def test_batch_refuses_before_any_work_and_honours_the_override(rf_files, pairs, tmp_path, capsys):
    import shutil

    p = pairs["paper"]
    dx, dy = p.spacing
    src = tmp_path / "data"
    src.mkdir()
    shutil.copy(rf_files["paper"], src / "a.rf")
    args = ["batch", str(src), "--task", "register", "--workers", "0", "--no-progress", "--spacing", f"{2 * dx:g}",
            str(dy)]
    rc = main(args + ["-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "a.rf: " in err and "states 40 MHz" in err, err
    assert not (tmp_path / "out").exists()                               # refused before any task ran
    # the override reaches the batch's reader too (before, its reader checks ran whatever the settings said)
    rc = main(args + ["-o", str(tmp_path / "out2"), "--no-orientation-check", "--maxiter", "3"])
    err = capsys.readouterr().err
    assert rc == 0 and "states 40 MHz" not in err, err
