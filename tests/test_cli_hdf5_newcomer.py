"""A research scanner's HDF5 export on the command line, as a first-time user meets it: RF as int16 frames with
their acquisition attributes (Hz, m/s, m), and the same frames demodulated to IQ (complex, decimated) with their
demodulation frequency.  What used to trip: `femreg batch` dropped --iq-frequency (every IQ recording refused),
`plot --reference` / `invert --images` read an IQ file at the result's RF step (refused with a false frequency
verdict naming a flag they did not have), a right --spacing on IQ drew a note that it was wrong, and IQ stored as
two datasets (I and Q) or as a compound of int16 fields was refused or read half as envelope data.  Small
simulated L7 pairs (forward.pairs); the in vivo recording only where it is found."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from scipy.signal import hilbert, resample_poly

from femreg.cli import main
from femreg.io import read_frames

from _track_loop import colorbar_labels
from test_io import INVIVO

C = 1540.0
SEQ = INVIVO / "seq299"
needs_invivo = pytest.mark.skipif(not (SEQ / "frame1.raw").is_file(), reason=f"in vivo data not found at {SEQ}")
#: IQ decimation, as the scanners' IQ exports (4 x the RF step)
Q = 4


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _iq(rf, dx, f_mhz, q=Q):
    """IQ of RF frames (n, axial, lateral): analytic signal shifted down by f (MHz), decimated q times."""
    z = dx * np.arange(rf.shape[-2])
    iq = hilbert(rf, axis=-2) * np.exp(-2j * np.pi * f_mhz * 2e3 * z / C)[:, None]
    return resample_poly(iq, 1, q, axis=-2).astype(np.complex64)


def _attrs(f, dx_mm, dy_mm, f_mhz, iq=False):
    """A scanner's acquisition attributes in SI units (Hz, m/s, m), as exported."""
    f.attrs["sampling_frequency"] = C / (2 * dx_mm * 1e-3)
    f.attrs["sound_speed"] = C
    f.attrs["element_pitch"] = dy_mm * 1e-3
    f.attrs["center_frequency"] = f_mhz * 1e6
    if iq:
        f.attrs["demodulation_frequency"] = f_mhz * 1e6


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """``rf.h5`` (int16 RF, 2 frames of a 1 % compression), ``iq.h5`` (its IQ, complex64, decimated 4x),
    ``iq_pair.h5`` (the IQ as int16 datasets I and Q), ``iq_compound.h5`` (one int16 compound of 'real', 'imag'),
    ``iq.npz`` (the IQ pair registered) and the numbers: dx (RF), dy, f (MHz)."""
    from forward import fields as F
    from forward.pairs import make_pair

    d = tmp_path_factory.mktemp("h5newcomer")
    p = make_pair(F.compression(0.01), probe="L7", size_mm=(12.0, 8.0), snr_db=30.0, seed=5)
    dx, dy = (float(v) for v in p.spacing)
    f = float(p.probe.f0_mhz)
    rf = np.stack([p.ref, p.mov])
    with h5py.File(d / "rf.h5", "w") as h:
        h["RFdata"] = np.round(rf * 20000 / np.abs(rf).max()).astype(np.int16)
        _attrs(h, dx, dy, f)
    iq = _iq(rf, dx, f)
    with h5py.File(d / "iq.h5", "w") as h:
        h["IQData"] = iq
        _attrs(h, Q * dx, dy, f, iq=True)
    scale = 20000 / np.abs(iq).max()
    with h5py.File(d / "iq_pair.h5", "w") as h:
        h["I"] = np.round(iq.real * scale).astype(np.int16)
        h["Q"] = np.round(iq.imag * scale).astype(np.int16)
        _attrs(h, Q * dx, dy, f, iq=True)
    comp = np.empty(iq.shape, np.dtype([("real", "<i2"), ("imag", "<i2")]))
    comp["real"], comp["imag"] = np.round(iq.real * scale), np.round(iq.imag * scale)
    with h5py.File(d / "iq_compound.h5", "w") as h:
        h["IQData"] = comp
        _attrs(h, Q * dx, dy, f, iq=True)
    iq_flags = ["--spacing", Q * dx, dy, "--iq-frequency", f"{f:.4f}"]
    assert main([str(a) for a in ["register", d / "iq.h5", "--pair", 0, 1, "-o", d / "iq.npz", "--no-progress",
                                  *iq_flags]]) == 0
    return {"dir": d, "dx": dx, "dy": dy, "f": f, "iq_flags": iq_flags}


# ---------------------------------------------------------------------------------------------- batch
def test_batch_passes_the_iq_frequency_on(scan, tmp_path, capsys):
    """Before: every IQ recording of a batch refused (exit 2) 'give the demodulation frequency', with it given."""
    d = scan["dir"]
    rc, out, err = _run(["batch", d / "iq.h5", "-o", tmp_path / "b", "--workers", 0, "--task", "register",
                         "--pair", 0, 1, "--no-progress", *scan["iq_flags"]], capsys)
    assert rc == 0, err
    rec = json.loads((tmp_path / "b" / "iq" / "pair_000-001.record.json").read_text())
    assert rec["status"] == "ok" and rec["ncc_after"] > 0.9, rec          # measured 0.99
    # the per-recording settings file takes the flag's name too
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "iq.h5").write_bytes((d / "iq.h5").read_bytes())
    (tmp_path / "in" / "iq.femreg.json").write_text(json.dumps({"iq-frequency": float(scan["iq_flags"][-1]),
                                                                "spacing": [Q * scan["dx"], scan["dy"]]}))
    rc, out, err = _run(["batch", tmp_path / "in", "-o", tmp_path / "b2", "--workers", 0, "--task", "register",
                         "--no-progress"], capsys)
    assert rc == 0, err


def test_batch_without_the_iq_frequency_still_says_what_to_pass(scan, tmp_path, capsys):
    rc, out, err = _run(["batch", scan["dir"] / "iq.h5", "-o", tmp_path / "b", "--workers", 0,
                         "--spacing", Q * scan["dx"], scan["dy"]], capsys)
    assert rc == 2 and "--iq-frequency" in err and err.count("\n") == 1, err


# ---------------------------------------------------------------------------------------------- spacing note
def test_the_right_iq_spacing_draws_no_note_and_a_wrong_one_does(scan, capsys):
    """The fields' sampling rate is the IQ samples': before, the remodulated RF step (dx) was held against it and
    a right --spacing got 'differs from what the file's fields imply (axial dx against 4 dx)'."""
    d = scan["dir"]
    rc, out, err = _run(["info", d / "iq.h5", *scan["iq_flags"]], capsys)
    assert rc == 0 and "differs from what the file's fields imply" not in err, err
    assert "complex64 as stored" in out and "complex complex64" not in out, out
    wrong = ["--spacing", 1.3 * Q * scan["dx"], scan["dy"], "--iq-frequency", scan["iq_flags"][-1],
             "--no-progress"]
    rc, out, err = _run(["info", d / "iq.h5", *wrong], capsys)
    assert "differs from what the file's fields imply" in err and "against" in err, err


# ---------------------------------------------------------------------------------------------- plot / invert
def test_plot_reference_reads_iq_at_its_own_sample_spacing(scan, tmp_path, capsys):
    """Before: exit 2, 'the IQ phase ... turns as for a 4x higher demodulation', as the result's RF step was
    taken for the IQ step."""
    d = scan["dir"]
    rc, out, err = _run(["plot", d / "iq.npz", "--reference", d / "iq.h5", "--iq-frequency", scan["iq_flags"][-1],
                         "-o", tmp_path / "p.png"], capsys)
    assert rc == 0 and (tmp_path / "p.png").is_file(), err
    assert "differs from what the file's fields imply" not in err, err


def test_invert_images_reads_iq_at_its_own_sample_spacing(scan, tmp_path, capsys):
    import argparse

    from femreg.cli._common import frames_on_result_grid
    from femreg.cli.invert_cmd import add_parser

    d = scan["dir"]
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(
        ["invert", str(d / "iq.npz"), "-o", str(tmp_path / "m.npz"), "--images", str(d / "iq.h5"),
         "--iq-frequency", scan["iq_flags"][-1]])
    res = np.load(d / "iq.npz")
    fr = frames_on_result_grid(args, d / "iq.h5", res["spacing"], res["shape"])
    assert fr.frames.shape[1:] == tuple(res["shape"]) and np.allclose(fr.spacing, res["spacing"], rtol=1e-6)
    assert args.spacing[0] == pytest.approx(Q * scan["dx"], rel=1e-6)


def test_the_iq_stand_in_spacing_needs_no_read_of_its_own(scan, tmp_path, monkeypatch):
    """The IQ sample count comes from the refusal of the file without a spacing (``frame_shape``): two reads, the
    refused one and the frames' (before: a third, in between, to count the IQ samples)."""
    import argparse

    import femreg.io
    from femreg.cli._common import _iq_stand_in, frames_on_result_grid
    from femreg.cli.plot_cmd import add_parser

    d = scan["dir"]
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["plot", str(d / "iq.npz"), "--reference", str(d / "iq.h5"),
                              "--iq-frequency", scan["iq_flags"][-1], "-o", str(tmp_path / "p.png")])
    res = np.load(d / "iq.npz")
    reads = []
    real = femreg.io.read_frames
    monkeypatch.setattr(femreg.io, "read_frames", lambda *a, **k: reads.append(a[0]) or real(*a, **k))
    fr = frames_on_result_grid(args, d / "iq.h5", res["spacing"], res["shape"])
    assert len(reads) == 2 and fr.frames.shape[1:] == tuple(res["shape"]), reads
    assert args.spacing[0] == pytest.approx(Q * scan["dx"], rel=1e-6)
    # frames stored lines first (--transpose): the samples are the file's second axis
    n_iq, n_rf = 51, 201
    stand = argparse.Namespace(modulation_frequency=5.0, transpose=True)
    assert _iq_stand_in(stand, (40, n_iq), [0.05, 0.2], (n_rf, 40)) == [0.05 * Q, 0.2]
    assert _iq_stand_in(stand, (n_iq, 40), [0.05, 0.2], (n_rf, 40)) == [0.05, 0.2]
    assert _iq_stand_in(argparse.Namespace(modulation_frequency=None), (n_iq, 40), [0.05, 0.2], (n_rf, 40)) \
        == [0.05, 0.2]


def test_plot_and_invert_take_no_orientation_check_with_their_frames_only(scan, tmp_path, capsys):
    """The IQ checks' messages name --no-orientation-check; plot and invert did not accept it (argparse: exit 2,
    'unrecognized arguments')."""
    d = scan["dir"]
    freq = ["--iq-frequency", scan["iq_flags"][-1]]
    rc, out, err = _run(["plot", d / "iq.npz", "--reference", d / "iq.h5", *freq, "--no-orientation-check",
                         "-o", tmp_path / "p.png"], capsys)
    assert rc == 0, err
    rc, out, err = _run(["plot", d / "iq.npz", "--no-orientation-check", "-o", tmp_path / "q.png"], capsys)
    assert rc == 2 and "applies to the frames of --reference" in err and not (tmp_path / "q.png").exists(), err
    rc, out, err = _run(["invert", d / "iq.npz", "--no-orientation-check", "-o", tmp_path / "m.npz"], capsys)
    assert rc == 2 and "applies to the frames of --images" in err and not (tmp_path / "m.npz").exists(), err


# ---------------------------------------------------------------------------------------------- IQ layouts
@pytest.mark.parametrize("name", ["iq_pair.h5", "iq_compound.h5"])
def test_iq_as_two_int16_halves_reads_as_the_complex_dataset(scan, name):
    """Before: 'several 2D/3D datasets (I, Q); choose one' / 'no 2D/3D numeric dataset found'; and --variable I
    read the in-phase half alone, passed as envelope data ('ready to register')."""
    d, f = scan["dir"], float(scan["iq_flags"][-1])
    sp = (Q * scan["dx"], scan["dy"])
    want = read_frames(d / "iq.h5", spacing=sp, modulation_frequency=f).frames
    for variable in ([None, "I", "Q"] if name == "iq_pair.h5" else [None]):
        fr = read_frames(d / name, spacing=sp, modulation_frequency=f, variable=variable)
        assert "iq" in fr.metadata and "complex int16" in fr.metadata["stored_dtype"]
        assert fr.frames.shape == want.shape
        rho = np.corrcoef(fr.frames.ravel(), want.ravel())[0, 1]
        assert rho > 0.9999, (variable, rho)                               # int16 rounding: measured 1 - 4e-8


@pytest.mark.parametrize("names", [("I_data", "Q_data"), ("rf_i", "rf_q"), ("Idata", "Qdata"),
                                   ("iq_real", "iq_imag"), ("acq/I", "acq/Q")])
def test_iq_halves_are_paired_by_their_names(tmp_path, names):
    from femreg.io.hdf5 import _datasets, _iq_pairs

    a = np.zeros((2, 40, 8), np.int16)
    with h5py.File(tmp_path / "x.h5", "w") as h:
        h[names[0]], h[names[1]] = a, a
        h["timestamps"] = np.arange(2.0)
        h["image"] = np.zeros((2, 40, 8), np.int16)       # no partner: not paired
    with h5py.File(tmp_path / "x.h5", "r") as h:
        assert _iq_pairs(_datasets(h)) == {names[0]: names[1]}


# ---------------------------------------------------------------------------------------------- in vivo
@needs_invivo
def test_invivo_iq_export_through_plot_without_spacing(tmp_path, capsys):
    """The in vivo frames 1 -> 2 of seq299 exported as a scanner would (IQ at 4.16 MHz, decimated 4x to 0.08 mm):
    registered, then drawn over their own B-mode with no --spacing (the result's, as for RF files)."""
    rf = np.stack([np.fromfile(SEQ / f"frame{k}.raw", "<f4").reshape(2000, 128) for k in (1, 2)]).astype(float)
    iq = _iq(rf, 0.02, 4.16)
    with h5py.File(tmp_path / "iq.h5", "w") as h:
        h["IQData"] = iq
        _attrs(h, 0.08, 0.2, 4.16, iq=True)
    flags = ["--iq-frequency", "4.16"]
    rc, out, err = _run(["register", tmp_path / "iq.h5", "--pair", 0, 1, "-o", tmp_path / "p.npz", "--spacing",
                         0.08, 0.2, "--no-progress", *flags], capsys)
    assert rc == 0 and "differs from what the file's fields imply" not in err, err
    rc, out, err = _run(["plot", tmp_path / "p.npz", "--reference", tmp_path / "iq.h5", "-o", tmp_path / "p.png",
                         *flags], capsys)
    assert rc == 0, err
    # the bright spot at 15, 20 mm typed in cm: measured (exit 0) with a note naming the numbers in mm
    rc, out, err = _run(["measure", tmp_path / "p.npz", "--inclusion", 1.5, 2.0, 0.3], capsys)
    assert rc == 0 and "narrower than one element" in out and "--inclusion 15 20 3" in out, out


# ---------------------------------------------------------------------------------------------- centimetres
def test_a_region_in_centimetres_gets_a_note(scan, capsys):
    """--depth 0.5 3.5 on a 40 mm in vivo frame (a scanner's display in cm) registered a 3 mm strip of the near
    field without a word (exit 0)."""
    import argparse

    from femreg.cli import _common

    fr = read_frames(scan["dir"] / "rf.h5", spacing=(scan["dx"], scan["dy"]))
    depth_mm = fr.spacing[0] * (fr.frames.shape[1] - 1)                   # 12 mm
    cases = [(dict(depth=[0.3, 1.1]), "--depth 3 11"), (dict(roi=["0.2", "1.0", "0.1", "0.7"]), "--roi 2 10 1 7"),
             (dict(depth=[3.0, 11.0]), None), (dict(depth=[0.3, 0.9 * depth_mm]), None),
             (dict(roi=["full"]), None), (dict(depth=[0.2, 2.0]), None)]      # 20 mm lies beyond the frame
    for kw, want in cases:
        args = argparse.Namespace(command="track", **kw)
        _common._note_region_in_centimetres(fr, "rf.h5", args)
        err = capsys.readouterr().err
        assert (f"in centimetres it would be {want} (mm)" in err) if want else err == "", (kw, err)


def test_measure_notes_an_inclusion_narrower_than_an_element(scan, capsys):
    d = scan["dir"]
    rc, out, err = _run(["measure", d / "iq.npz", "--inclusion", 5, 4, 0.2], capsys)
    # ten times it lies outside this 12 x 8 mm mesh: no centimetre hint (the in vivo test below has one)
    assert rc == 0 and "narrower than one element" in out and "centimetres" not in out, out
    rc, out, err = _run(["measure", d / "iq.npz", "--inclusion", 5, 4, 1.5, "--json", d / "m.json"], capsys)
    assert rc == 0 and "narrower" not in out, out
    bounds = json.loads((d / "m.json").read_text())["mesh_bounds_mm"]
    assert all(v == round(v, 6) for v in bounds.values()), bounds


# ---------------------------------------------------------------------------------------------- pictures
def test_the_quality_map_names_the_frames_it_compares(scan, tmp_path, monkeypatch, capsys):
    """Three frame_KKK_quality.png of a track looked alike: their title did not say which pair each one is."""
    import matplotlib.pyplot as plt

    import femreg.plot as fplot

    assert fplot.quality_pair({"frame": 5, "increment": 0, "mode": "accumulate"}) == "frame 4 -> 5"
    assert fplot.quality_pair({"frame": 1, "increment": 0, "mode": "accumulate"}) == "frame 0 -> 1"
    assert fplot.quality_pair({"frame": 3, "increment": 0, "mode": "direct"}) == "frame 0 -> 3"
    assert fplot.quality_pair({"pair": np.array([2, 4])}) == "frames 2 -> 4"
    assert fplot.quality_pair({}) == ""
    titles = []
    real = fplot.plot_quality

    def spy(*a, **kw):
        fig = real(*a, **kw)
        titles.append(fig.axes[0].get_title())
        return fig

    monkeypatch.setattr(fplot, "plot_quality", spy)
    rc, out, err = _run(["plot", scan["dir"] / "iq.npz", "-o", tmp_path / "p.png"], capsys)
    plt.close("all")
    assert rc == 0 and titles and titles[0].startswith("registration quality, frames 0 -> 1 "), titles


def test_a_swapped_spacing_for_the_reference_is_named_swapped(scan, tmp_path):
    """plot --reference / invert --images with --spacing typed lateral first: before, 'not the frames it was
    registered from, or a wrong --spacing', which sends a user looking for another file."""
    import argparse

    from femreg.cli._common import frames_on_result_grid
    from femreg.cli.plot_cmd import add_parser
    from femreg.errors import InputError

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    dx, dy = scan["dx"], scan["dy"]
    args = parser.parse_args(["plot", "r.npz", "--reference", str(scan["dir"] / "rf.h5"),
                              "--spacing", str(dy), str(dx)])
    with pytest.raises(InputError, match=rf"look swapped: leave --spacing out .* or pass --spacing {dx:g} {dy:g}"):
        frames_on_result_grid(args, scan["dir"] / "rf.h5", (dx, dy), None)


def test_a_modulus_colour_bar_over_decades_labels_its_ends():
    """The in vivo seq299 frame 0 -> 5 modulus (1-99 % range 0.17-86 x the median) had its colour bar labelled 1
    and 10 only: nothing near either end."""
    labels = colorbar_labels([0.174, 85.8], 0.174, 85.8)
    assert labels == ["0.2", "1", "3", "10", "50"], labels
