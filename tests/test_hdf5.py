"""Plain HDF5 files of RF frames: the layouts Python and MATLAB exports write, dataset choice, spacing from the file
or a hint from its header fields, IQ, and the CLI's answers."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest

from femreg.errors import FileFormatError, InputError
from femreg.io import read_frames
from femreg.io.checks import iq_frequency_hint, spacing_hint

h5py = pytest.importorskip("h5py")


@pytest.fixture(scope="module")
def pair():
    from forward import fields as F
    from forward.pairs import make_pair

    return make_pair(F.compression(0.01), probe="L7", size_mm=(12.0, 10.0), snr_db=30.0, seed=4)


def _stack(pair):
    return np.stack([pair.ref, pair.mov]).astype(np.float32)       # (2, axial, lateral)


def _write(path, arr, name="rf", **attrs):
    with h5py.File(path, "w") as f:
        ds = f.create_dataset(name, data=arr)
        for k, v in attrs.items():
            ds.attrs[k] = v


@pytest.mark.parametrize("layout", ["numpy", "matlab-h5write", "frames-last"])
def test_layouts_read_as_frames(pair, tmp_path, layout):
    rf = _stack(pair)
    stored = {"numpy": rf, "matlab-h5write": rf.transpose(0, 2, 1), "frames-last": np.moveaxis(rf, 0, -1)}[layout]
    path = tmp_path / "scan.h5"
    _write(path, stored, spacing=np.asarray(pair.spacing))
    fr = read_frames(path)
    assert fr.metadata["format"] == "hdf5" and fr.spacing == pytest.approx(pair.spacing)
    np.testing.assert_array_equal(fr.frames, rf)
    # the layout note says what was done (nothing for numpy's own order)
    assert ("transposed" in fr.metadata.get("layout", "")) == (layout == "matlab-h5write")
    assert ("frames on the last axis" in fr.metadata.get("layout", "")) == (layout == "frames-last")


def test_dataset_choice_and_errors(pair, tmp_path):
    rf = _stack(pair)
    path = tmp_path / "acq.hdf5"
    with h5py.File(path, "w") as f:
        f.create_dataset("acq/beamformed", data=rf)
        f.create_dataset("acq/envelope", data=np.abs(rf))
        f.attrs["spacing"] = pair.spacing
    with pytest.raises(FileFormatError, match="several 2D/3D datasets.*--variable"):
        read_frames(path)
    assert read_frames(path, variable="acq/beamformed").frames.shape == rf.shape
    with pytest.raises(FileFormatError, match="missing dataset 'nope'; available: acq/beamformed, acq/envelope"):
        read_frames(path, variable="nope")
    # an HDF5 file under another name is recognised by its content
    other = tmp_path / "scan.dat5"
    other.write_bytes(path.read_bytes())
    assert read_frames(other, variable="/acq/beamformed").metadata["format"] == "hdf5"
    # MATLAB's -v7.3 under an HDF5 name keeps MATLAB's axis order
    from femreg.io.matlab import write_mat

    write_mat(tmp_path / "m.h5", rf, pair.spacing, version="7.3")
    fr = read_frames(tmp_path / "m.h5")
    assert fr.metadata["format"] == "mat-v7.3"
    np.testing.assert_array_equal(fr.frames, rf)
    bad = tmp_path / "cut.h5"
    bad.write_bytes(path.read_bytes()[:600])
    with pytest.raises(FileFormatError, match="cut.h5"):
        read_frames(bad)


def test_spacing_hint_from_header_fields(pair, tmp_path):
    rf = _stack(pair)
    dx, dy = pair.spacing
    fs = 1540.0 / (2 * dx * 1e-3)                        # Hz, as scanners record it
    path = tmp_path / "scan.h5"
    _write(path, rf, fs=fs, pitch=dy * 1e-3, c=1540.0)
    with pytest.raises(InputError, match="spacing unknown") as err:
        read_frames(path)
    assert f"--spacing {dx:.4g} {dy:.4g}" in str(err.value), str(err.value)
    assert read_frames(path, spacing=pair.spacing).metadata["fields"]["pitch"] == pytest.approx(dy * 1e-3)
    # npz and MATLAB files: their scalar variables
    np.savez(tmp_path / "scan.npz", rf=rf, fs_MHz=fs / 1e6, pitch_mm=dy)
    import scipy.io

    scipy.io.savemat(tmp_path / "scan.mat", {"rf": np.moveaxis(rf, 0, -1), "fs": fs, "pitch": dy * 1e-3})
    for name in ("scan.npz", "scan.mat"):
        with pytest.raises(InputError, match=f"--spacing {dx:.4g} {dy:.4g}"):
            read_frames(tmp_path / name)
    # units from the names, else from the magnitude; with one of the two the other is named as missing
    assert "--spacing 0.02 0.3" in spacing_hint({"fs_MHz": 38.5, "pitch_mm": 0.3})
    assert "--spacing 0.025 0.2" in spacing_hint({"SamplingFrequency": 30.8e6, "Pitch": 2e-4, "c": 1540})
    only_fs = spacing_hint({"fs": 40e6, "c": 1540.0})
    assert "--spacing 0.01925 DY" in only_fs and "line pitch" in only_fs, only_fs
    assert "--spacing DX 0.3 " in spacing_hint({"pitch": 0.3, "name": "x"})
    assert spacing_hint({"fc": 5.0, "name": "x"}) == ""
    assert "--iq-frequency 5.2 " in iq_frequency_hint({"demodulation_frequency": 5.2e6})
    # a centre frequency is only the usual demodulation frequency: named as such, and a demodulation field wins
    centre = iq_frequency_hint({"fc": 5.2, "fs": 20.0})
    assert "--iq-frequency 5.2 " in centre and "centre frequency" in centre and "check it" in centre, centre
    assert "--iq-frequency 6 " in iq_frequency_hint({"f0": 5.2e6, "fDemod_MHz": 6.0})
    assert iq_frequency_hint({"f0": 2e9}) == ""                          # no ultrasound carrier


def test_iq_dataset_needs_its_frequency(pair, tmp_path):
    from scipy.signal import hilbert

    dx, dy = pair.spacing
    f0 = pair.probe.f0_mhz
    z = dx * np.arange(pair.ref.shape[0])
    iq = (hilbert(_stack(pair), axis=1) * np.exp(-2j * np.pi * f0 * 2e3 * z / 1540.0)[:, None]).astype(np.complex64)
    path = tmp_path / "iq.h5"
    _write(path, iq, spacing=np.asarray(pair.spacing), f_demod_MHz=f0)
    with pytest.raises(InputError, match=f"its fields suggest --iq-frequency {f0:g} "):
        read_frames(path)
    fr = read_frames(path, modulation_frequency=f0)
    up = fr.metadata["iq"]["upsampled"]
    c = np.corrcoef(fr.frames[0][::up].ravel(), pair.ref.ravel())[0, 1]
    # remodulated the RF comes back (measured correlation 1.000 on its own samples)
    assert fr.metadata["stored_dtype"] == "complex64" and c > 0.98, (c, up)


def test_cli_info_hint_and_swapped_spacing(pair, tmp_path, capsys):
    from femreg.cli import main

    def cli(argv):   # in this process: `python -m femreg` itself is tests/test_cli_io.py's
        rc = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(argv, rc, out, err)

    rf = _stack(pair)
    dx, dy = pair.spacing
    path = tmp_path / "scan.h5"
    _write(path, np.round(rf.transpose(0, 2, 1) * 1000).astype(np.int16), fs_MHz=1.54 / (2 * dx), pitch_mm=dy)
    info = cli(["info", path])
    assert info.returncode == 1 and f"--spacing {dx:.4g} {dy:.4g}" in info.stdout, info
    assert "format    hdf5" in info.stdout and "transposed" in info.stdout and "int16" in info.stdout
    bad = cli(["register", path, "--spacing", f"{dy}", f"{dx}", "-o", tmp_path / "r.npz"])
    assert bad.returncode == 2 and "swapped" in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
