"""IQ frames saved from MATLAB after a Verasonics-style acquisition, on the command line as a first-time user meets
them: ``IData`` and ``QData`` (real arrays ``(axial, lateral, frame)``) beside the ``Trans`` / ``Receive`` structs
(``Trans.frequency``, ``Trans.spacingMm``, ``Receive.demodFrequency``, ``Receive.decimSampleRate``: the RF
sampling rate, the IQ decimated 2x after it).  What used to trip: the pair was refused as two candidate variables
and either half alone read as real data; the struct's pitch and sampling rate were not read; the spacing of the
header's sampling rate (2x too small for this IQ) was refused as a wrong demodulation frequency, and following
that advice (``--iq-frequency`` twice the file's) registered with every depth and displacement halved,
``success=True``.  A small simulated 5 MHz pair (forward.pairs)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.io
from scipy.signal import hilbert, resample_poly

from femreg.cli import main
from femreg.errors import InputError
from femreg.io import read_frames
from femreg.io.checks import header_frequencies, spacing_suggestion
from femreg.orientation import OrientationError, check_sampling

C = 1540.0
F0, FS, PITCH, Q = 5.0, 20.0, 0.3, 2        # MHz, MHz (RF), mm, IQ decimation
DX_FS = C * 1e-3 / (2 * FS)                 # mm: the header rate's step, half the IQ samples'
DX_IQ = Q * DX_FS
LEVEL = 0.01


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """``iq.mat`` (v5: IData, QData single, Trans, Receive) of a 1 % compressed pair, 2-22 mm x 12 mm, and
    ``iq73.mat`` (the same as MATLAB's -v7.3)."""
    import h5py

    from forward import fields as F
    from forward.pairs import Probe, make_pair

    d = tmp_path_factory.mktemp("matlab_iq")
    pair = make_pair(F.compression(LEVEL), Probe(F0, FS, PITCH, 1.0, 2.0, name="L5"), size_mm=(20.0, 12.0),
                     snr_db=30.0, seed=3, top_mm=2.0)
    rf = np.stack([pair.ref, pair.mov])
    z = pair.spacing[0] * np.arange(rf.shape[1])
    iq = hilbert(rf, axis=1) * np.exp(-2j * np.pi * F0 * 2e3 * z / C)[None, :, None]
    iq = resample_poly(iq, 1, Q, axis=1)
    iq = np.moveaxis(iq / np.abs(iq).max(), 0, -1)          # MATLAB: (axial, lateral, frame)
    i, q = iq.real.astype(np.float32), iq.imag.astype(np.float32)
    trans = {"name": "L5", "frequency": F0, "spacingMm": PITCH}
    receive = {"demodFrequency": F0, "decimSampleRate": FS}
    scipy.io.savemat(str(d / "iq.mat"), {"IData": i, "QData": q, "Trans": trans, "Receive": receive})
    from femreg.io.matlab import write_mat

    write_mat(d / "iq73.mat", np.moveaxis(i, -1, 0), None, None, variable="IData", version="7.3")
    with h5py.File(d / "iq73.mat", "r+") as f:
        ds = f.create_dataset("QData", data=np.ascontiguousarray(q.T))
        ds.attrs["MATLAB_class"] = np.bytes_("single")
    return {"dir": d, "pair": pair}


@pytest.mark.parametrize("name", ["iq.mat", "iq73.mat"])
def test_idata_and_qdata_are_read_as_one_complex_array(scan, name):
    """Before: 'several 2D/3D variables (IData, QData)', and --variable IData read the in-phase half as RF."""
    path = scan["dir"] / name
    with pytest.raises(InputError, match=r"'IData' \+ 1j 'QData'.*--iq-frequency") as err:
        read_frames(path, spacing=(DX_IQ, PITCH))
    stored = err.value.iq_frames
    assert np.iscomplexobj(stored.frames) and stored.frames.shape[0] == 2, stored.frames.shape
    # the RF the pair remodulates to: the same whichever half --variable names
    a = read_frames(path, spacing=(DX_IQ, PITCH), modulation_frequency=F0)
    b = read_frames(path, spacing=(DX_IQ, PITCH), modulation_frequency=F0, variable="QData")
    assert np.isrealobj(a.frames) and a.metadata["iq"]["iq_spacing_mm"] == DX_IQ
    np.testing.assert_array_equal(a.frames, b.frames)
    # the RF's carrier is the demodulation frequency's: the remodulated frame correlates with the simulated RF
    rf, stride = scan["pair"].ref, a.metadata["iq"]["upsampled"] // Q      # the RF at the simulated step
    mine = a.frames[0, ::stride]
    n = min(rf.shape[0], mine.shape[0]) - 8
    r = np.corrcoef(rf[8:n].ravel(), mine[8:n].ravel())[0, 1]
    assert r > 0.9, r           # measured 0.99


def test_a_probe_structs_spacing_and_frequency_are_read():
    """Verasonics' Trans.spacingMm / Trans.frequency and Receive.decimSampleRate; before: no suggestion at all."""
    sug = spacing_suggestion({"Trans/spacingMm": PITCH, "Receive/decimSampleRate": FS})
    assert (sug.dx, sug.dy) == (f"{DX_FS:.4g}", f"{PITCH:g}"), sug
    assert "IQ" not in sug.why_x
    assert "decimated q times" in spacing_suggestion({"Receive/decimSampleRate": FS}, iq=True).why_x
    # a field named spacing outside a probe's struct is no pitch (it may be any spacing)
    assert spacing_suggestion({"Receive/spacingMm": PITCH}) is None
    # Verasonics' bare Trans.spacing is in wavelengths: no pitch in mm
    assert spacing_suggestion({"Trans/spacing": 0.97}) is None
    known = header_frequencies({"fields": {"Trans/frequency": F0, "Receive/demodFrequency": F0}})
    assert known["transmit_mhz"][0] == F0 and known["demod_mhz"][0] == F0, known


def test_info_suggests_the_iq_samples_spacing(scan, capsys):
    """The header's rate is the RF's; the IQ phases between the frames show the 2x decimation.  Before: 'no
    spacing found' (v5 structs unread); with the struct names read, c / (2 fs), half the IQ samples' step."""
    rc, out, err = _run(["info", scan["dir"] / "iq.mat"], capsys)
    assert rc == 1 and f"its fields suggest --spacing {DX_IQ:.5g} {PITCH:g}" in out, out
    assert "IQ decimated 2x after sampling" in out and "--iq-frequency 5 " in out, out


def test_the_header_rates_spacing_is_refused_naming_the_iq_spacing(scan, capsys):
    """Before: 'turns as for a 10 MHz demodulation, not the 5 MHz given ... give the demodulation frequency the
    scanner recorded'; following it (--iq-frequency 10) registered with depths and displacements halved, exit 0."""
    mat = scan["dir"] / "iq.mat"
    rc, out, err = _run(["register", mat, "--pair", 0, 1, "--spacing", DX_FS, PITCH, "--iq-frequency", F0,
                         "-o", scan["dir"] / "rate.npz"], capsys)
    assert rc == 2 and "which is the demodulation frequency the file states" in err, err
    assert f"looks 2 times too small" in err and f"--spacing {DX_IQ:.5g} {PITCH:g}" in err, err
    assert "IQ decimated 2x after sampling" in err, err
    rc, out, err = _run(["register", mat, "--pair", 0, 1, "--spacing", DX_FS, PITCH, "--iq-frequency", 2 * F0,
                         "-o", scan["dir"] / "rate.npz"], capsys)
    assert rc == 2 and f"the file states the demodulation frequency {F0:g} MHz" in err, err
    assert f"pass --iq-frequency {F0:g}," in err, err
    assert not (scan["dir"] / "rate.npz").exists()


def test_the_right_spacing_registers_without_a_note(scan, capsys):
    import femreg

    out_file = scan["dir"] / "right.npz"
    rc, out, err = _run(["register", scan["dir"] / "iq.mat", "--pair", 0, 1, "--spacing", DX_IQ, PITCH,
                         "--iq-frequency", F0, "-o", out_file, "--no-progress"], capsys)
    assert rc == 0 and "note" not in err, err
    res = femreg.load_result(out_file)
    exx = res.on_grid()["exx"]
    # measured -1.0 %: a spacing off by 2 gives the same strain but halves every depth, so check the depth too
    assert abs(np.nanmedian(exx) + LEVEL) < 0.05 * LEVEL, np.nanmedian(exx)
    depth = res.pixel_points()[:, 0].max() - res.pixel_points()[:, 0].min()
    assert abs(depth - 20.0) < 0.5, depth


def test_an_iq_spacing_no_decimation_explains_is_noted(scan):
    fr = read_frames(scan["dir"] / "iq.mat", spacing=(1.5 * DX_FS, PITCH), modulation_frequency=F0,
                     check_orientation=False)
    notes = check_sampling(fr, (1.5 * DX_FS, PITCH))
    assert len(notes) == 1 and "1.5 times c / (2 fs)" in notes[0] and "no whole decimation" in notes[0], notes
    fr = read_frames(scan["dir"] / "iq.mat", spacing=(DX_IQ, PITCH), modulation_frequency=F0,
                     check_orientation=False)
    assert check_sampling(fr, (DX_IQ, PITCH)) == []
    with pytest.raises(OrientationError, match="demodulation frequency 5 MHz") as err:
        read_frames(scan["dir"] / "iq.mat", spacing=(DX_IQ, PITCH), modulation_frequency=1.3 * F0)
    assert err.value.problem == "iq-frequency"


def test_a_verasonics_section_axis_is_dropped(scan, tmp_path, capsys):
    """IData{1} / ImgData{1} are (axial, lateral, 1, frame).  Before: 'no 3D/4D numeric variable found' (info) and
    'volumes take --spacing DX DY DZ' (register): the one-long third axis read as a volume's."""
    d = scipy.io.loadmat(str(scan["dir"] / "iq.mat"))
    path = tmp_path / "sections.mat"
    scipy.io.savemat(str(path), {"IData": d["IData"][:, :, None, :], "QData": d["QData"][:, :, None, :],
                                 "Trans": d["Trans"], "Receive": d["Receive"]})
    rc, out, err = _run(["info", path, "--spacing", DX_IQ, PITCH, "--iq-frequency", F0], capsys)
    assert rc == 0 and "(axial, lateral, 1, frame): 2 frames of" in out, (out, err)
    a = read_frames(path, spacing=(DX_IQ, PITCH), modulation_frequency=F0)
    b = read_frames(scan["dir"] / "iq.mat", spacing=(DX_IQ, PITCH), modulation_frequency=F0)
    np.testing.assert_array_equal(a.frames, b.frames)


@pytest.mark.parametrize("factor, words", [(2.0, "2 times too large"), (1 / 3, "3 times too small")])
def test_an_iq_spacing_off_by_a_factor_is_named(scan, capsys, factor, words):
    """Before: refused as a wrong demodulation frequency (the phases turn as for f / factor)."""
    rc, out, err = _run(["info", scan["dir"] / "iq.mat", "--spacing", f"{factor * DX_IQ:.6g}", PITCH,
                         "--iq-frequency", F0], capsys)
    assert rc == 1 and words in out and f"pass --spacing {DX_IQ:.5g} {PITCH:g}" in out, out


def test_a_struct_arrays_shared_fields_are_read(scan, tmp_path, capsys):
    """Verasonics' Receive is a struct array, one element per acquisition.  Before: none of its fields read, so
    neither the sampling rate nor the demodulation frequency was suggested."""
    d = scipy.io.loadmat(str(scan["dir"] / "iq.mat"))
    rec = np.zeros((1, 3), dtype=[("demodFrequency", "O"), ("decimSampleRate", "O"), ("startDepth", "O")])
    for k in range(3):
        rec[0, k] = (F0, FS, 0.5 * k)                  # startDepth differs between the elements: left out
    path = tmp_path / "array.mat"
    scipy.io.savemat(str(path), {"IData": d["IData"], "QData": d["QData"], "Trans": d["Trans"], "Receive": rec})
    fields = read_frames(path, spacing=(DX_IQ, PITCH), modulation_frequency=F0).metadata["fields"]
    assert fields["Receive/demodFrequency"] == F0 and fields["Receive/decimSampleRate"] == FS, fields
    assert "Receive/startDepth" not in fields, fields
    rc, out, err = _run(["info", path], capsys)
    assert rc == 1 and f"--spacing {DX_IQ:.5g} {PITCH:g}" in out and "Receive/demodFrequency" in out, out


@pytest.mark.parametrize("factor", [5.0, 6.0])
def test_an_axial_spacing_past_the_pitch_is_not_taken_for_a_swap(scan, capsys, factor):
    """An axial spacing 5-6 times too large (0.385 / 0.462 mm, past the 0.3 mm pitch) narrows the speckle's aspect
    (measured lateral / axial 0.87 / 0.64) as exchanged spacings do.  Before: 'the axial and lateral spacings look
    swapped: pass --spacing 0.3 0.385', itself wrong (0.3 mm is 7.79 times the header rate's step, no decimation);
    the IQ phases at that rate show the 2x decimation, so the refusal names 0.077."""
    out_file = scan["dir"] / f"big{factor:g}.npz"
    rc, out, err = _run(["register", scan["dir"] / "iq.mat", "--pair", 0, 1, "--spacing", f"{factor * DX_IQ:.6g}",
                         PITCH, "--iq-frequency", F0, "-o", out_file], capsys)
    assert rc == 2 and "look swapped" not in err and f"--spacing {PITCH:g} " not in err, err
    assert f"looks {factor:g} times too large, not swapped" in err, err
    assert f"pass --spacing {DX_IQ:.5g} {PITCH:g}" in err and "IQ decimated 2x" in err, err
    assert not out_file.exists()


def test_exchanged_spacings_are_still_named_a_swap(scan, capsys):
    rc, out, err = _run(["register", scan["dir"] / "iq.mat", "--pair", 0, 1, "--spacing", PITCH, DX_IQ,
                         "--iq-frequency", F0, "-o", scan["dir"] / "swap.npz"], capsys)
    assert rc == 2 and "look swapped" in err and f"pass --spacing {DX_IQ:g} {PITCH:g}" in err, err


def test_without_phases_a_swap_unlike_the_header_is_not_suggested(scan):
    """One frame: no phases to read the decimation from; exchanged, the axial 0.3 mm would be 7.79 times the
    header rate's step (over 2 % from a whole decimation), so no swap is named."""
    import dataclasses

    from femreg.orientation import check_remodulated

    fr = read_frames(scan["dir"] / "iq.mat", spacing=(5 * DX_IQ, PITCH), modulation_frequency=F0,
                     check_orientation=False)
    with pytest.raises(OrientationError, match="no whole decimation") as err:
        check_remodulated(dataclasses.replace(fr, frames=fr.frames[:1]))
    assert err.value.problem == "iq-spacing" and "look swapped" not in str(err.value), str(err.value)
    with pytest.raises(OrientationError, match="look swapped"):      # the same frame with exchanged spacings
        fs = read_frames(scan["dir"] / "iq.mat", spacing=(PITCH, DX_IQ), modulation_frequency=F0,
                         check_orientation=False)
        check_remodulated(dataclasses.replace(fs, frames=fs.frames[:1]))
