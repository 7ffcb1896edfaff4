"""IQ (complex baseband) frames: remodulated to RF by every reader that stores complex arrays, refused without
their modulation frequency, swapped spacings caught by the speckle aspect, registered like the RF they came from."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest
from scipy.signal import hilbert, resample_poly

import femreg
from femreg.cli import main
from femreg.errors import InputError
from femreg.io import read_frames
from femreg.io.iq import remodulate
from femreg.orientation import OrientationError

C = 1540.0


def _cli(argv, capsys):
    """``femreg ARGV`` in this process: exit code, stdout and stderr as a finished process has them."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(argv, rc, out, err)


def _iq(rf, dx, f_mhz, q):
    """IQ of RF frames (n, axial, lateral): analytic signal shifted down by f, decimated by q along depth."""
    z = dx * np.arange(rf.shape[-2])
    iq = hilbert(rf, axis=-2) * np.exp(-2j * np.pi * f_mhz * 2e3 * z / C)[:, None]
    return resample_poly(iq, 1, q, axis=-2).astype(np.complex64)


def _pair_iq(pair, q=3):
    """(IQ of the pair's two frames decimated q times, dx, dy, f MHz)."""
    dx, dy = pair.spacing
    f = pair.probe.f0_mhz
    return _iq(np.stack([pair.ref, pair.mov]), dx, f, q), dx, dy, f


@pytest.fixture(scope="module")
def pair():
    from forward import fields as F
    from forward.pairs import make_pair

    return make_pair(F.compression(0.01), probe="L7", size_mm=(16.0, 14.0), snr_db=30.0, seed=3)


def _write_mat73(path, iq_stack, spacing):
    """A MATLAB -v7.3 file as MATLAB writes one: IQ(axial, lateral, frame) int16 complex, stored transposed as a
    compound of 'real' and 'imag'."""
    import h5py

    t = np.moveaxis(iq_stack, 0, -1).T                      # HDF5 (row-major) view of the column-major array
    scale = 20000.0 / np.abs(t).max()
    arr = np.empty(t.shape, np.dtype([("real", "<i2"), ("imag", "<i2")]))
    arr["real"], arr["imag"] = np.round(t.real * scale), np.round(t.imag * scale)
    with h5py.File(path, "w", userblock_size=512) as f:
        f.create_dataset("IQData", data=arr).attrs["MATLAB_class"] = np.bytes_("int16")
        f.create_dataset("spacing", data=np.asarray(spacing, float)[:, None]).attrs["MATLAB_class"] = \
            np.bytes_("double")
    hdr = b"MATLAB 7.3 MAT-file, Platform: PCWIN64, Created on: Fri Dec  4 10:00:00 2026 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write(hdr.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM")


def test_remodulate_restores_the_rf(pair):
    dx = pair.spacing[0]
    f = pair.probe.f0_mhz
    iq = _iq(pair.ref[None], dx, f, 3)[0]                   # 3 x 0.019 mm: 1.8 IQ samples per RF period
    rf, step, up = remodulate(iq, 3 * dx, f)
    assert up == int(np.ceil(8 * 3 * dx / (C / (2e3 * f)))) and step == pytest.approx(3 * dx / up)
    ref = pair.ref[: (iq.shape[0] - 1) * 3 + 1]
    # resample the restored RF onto the original grid for the comparison
    orig = np.arange(ref.shape[0]) * dx
    back = np.stack([np.interp(orig, np.arange(rf.shape[0]) * step, rf[:, j]) for j in range(rf.shape[1])], 1)
    rho = np.corrcoef(back[20:-20].ravel(), ref[20:-20].ravel())[0, 1]
    assert rho > 0.99, rho                                  # measured 0.9994
    with pytest.raises(InputError, match="complex"):
        remodulate(rf, step, f)
    with pytest.raises(InputError, match="modulation frequency"):
        remodulate(iq, dx, -1.0)


@pytest.mark.parametrize("fmt", ["npz", "mat5", "mat73"])
def test_readers_remodulate_complex_frames(pair, tmp_path, fmt):
    import scipy.io

    iq, dx, dy, f = _pair_iq(pair)
    sp = (3 * dx, dy)
    path = tmp_path / f"iq.{'npz' if fmt == 'npz' else 'mat'}"
    if fmt == "npz":
        np.savez(path, rf=iq, spacing=sp)
    elif fmt == "mat5":
        scipy.io.savemat(path, {"rf": np.moveaxis(iq, 0, -1), "spacing": sp})
    else:
        _write_mat73(path, iq, sp)
    with pytest.raises(InputError, match="--iq-frequency"):
        read_frames(path)
    fr = read_frames(path, modulation_frequency=f)
    assert fr.frames.dtype == np.float32 and fr.n_frames == 2
    assert fr.metadata["iq"]["iq_samples"] == iq.shape[1] and fr.metadata["remodulated"]
    up = fr.metadata["iq"]["upsampled"]
    assert fr.frames.shape[1] == (iq.shape[1] - 1) * up + 1 and fr.spacing == pytest.approx((3 * dx / up, dy))
    # the carrier is back where the probe put it
    from femreg.orientation import diagnose

    rep = diagnose(fr.frames[0], fr.spacing)
    assert not rep.problem and abs(rep.frequency_mhz / f - 1) < 0.15, rep.frequency_mhz


def test_modulation_frequency_refused_for_rf(tmp_path, pair):
    path = tmp_path / "rf.npz"
    np.savez(path, rf=pair.ref, spacing=pair.spacing)
    with pytest.raises(InputError, match="RF, not IQ"):
        read_frames(path, modulation_frequency=7.5)


def test_swapped_iq_spacing_is_refused(pair, tmp_path):
    dx, dy = pair.spacing
    f = pair.probe.f0_mhz
    iq = _iq(pair.ref[None], dx, f, 3)
    path = tmp_path / "iq.npy"
    np.save(path, iq)
    with pytest.raises(OrientationError, match="look swapped") as err:
        read_frames(path, spacing=(dy, 3 * dx), modulation_frequency=f)
    assert err.value.problem == "swapped" and f"--spacing {3 * dx:g} {dy:g}" in str(err.value)
    read_frames(path, spacing=(3 * dx, dy), modulation_frequency=f)            # the right order passes
    read_frames(path, spacing=(dy, 3 * dx), modulation_frequency=f, check_orientation=False)


def test_iq_pair_registers_like_its_rf(pair):
    iq, dx, dy, f = _pair_iq(pair)
    rf, step, _ = remodulate(iq, 3 * dx, f, axis=1)
    kw = dict(regularizer="momentum-stress")
    r_iq = femreg.register(rf[0], rf[1], spacing=(step, dy), origin=pair.origin, **kw)
    r_rf = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, **kw)
    assert r_iq.success and r_rf.success
    pts = r_rf.pixel_points()[::7]
    e_iq, e_rf = r_iq.strain(pts)[:, 0], r_rf.strain(pts)[:, 0]
    ok = np.isfinite(e_iq) & np.isfinite(e_rf)
    err_iq = np.sqrt(np.mean((e_iq[ok] + 0.01) ** 2)) / 0.01
    err_rf = np.sqrt(np.mean((e_rf[ok] + 0.01) ** 2)) / 0.01
    # measured: IQ 0.00073, RF 0.00064 (axial strain RMS error relative to the 1 % compression)
    assert err_iq < 2.0 * err_rf + 0.005, (err_iq, err_rf)


def test_cli_info_and_register_on_iq(pair, tmp_path, capsys):
    iq, dx, dy, f = _pair_iq(pair)
    path = tmp_path / "scan.mat"
    _write_mat73(path, iq, (3 * dx, dy))
    info = _cli(["info", path], capsys)          # in this process: `python -m femreg` is tests/test_cli_io.py's
    assert info.returncode == 1 and "--iq-frequency" in info.stdout and "complex int16" in info.stdout, info
    # femreg info names what register would refuse (exit 1): exchanged spacings, another frequency; else ready
    for extra, said, rc in (([f"{dy}", f"{3 * dx}"], "look swapped", 1), ([f"{3 * dx}", f"{dy}"], "ready", 0)):
        got = _cli(["info", path, "--iq-frequency", f"{f}", "--spacing"] + extra, capsys)
        assert got.returncode == rc and said in got.stdout, got
    got = _cli(["info", path, "--iq-frequency", f"{1.2 * f}"], capsys)
    assert got.returncode == 1 and "MHz demodulation" in got.stdout, got
    bad = _cli(["register", path, "--iq-frequency", f"{f}", "--spacing", f"{dy}", f"{3 * dx}",
                "-o", tmp_path / "r.npz"], capsys)
    assert bad.returncode == 2 and "look swapped" in bad.stderr and "Traceback" not in bad.stderr, bad.stderr


def test_directory_of_iq_frames_is_one_stack(pair, tmp_path):
    iq, dx, dy, f = _pair_iq(pair)
    for k in range(2):
        np.save(tmp_path / f"frame{k + 1}.npy", iq[k])
    fr = read_frames(tmp_path, spacing=(3 * dx, dy), modulation_frequency=f)
    assert fr.n_frames == 2 and fr.metadata["format"] == "directory of npy" and fr.metadata["iq"]["upsampled"] > 1
    with pytest.raises(InputError, match="IQ data") as err:
        read_frames(tmp_path, spacing=(3 * dx, dy))
    assert err.value.iq_frames.n_frames == 2        # femreg info describes the whole folder


def test_sign_convention_is_checked(pair, tmp_path, capsys):
    from femreg.io.iq import iq_convention

    iq, dx, dy, f = _pair_iq(pair)
    std = iq_convention(iq[0], iq[1], 3 * dx, f)
    conj = iq_convention(np.conj(iq[0]), np.conj(iq[1]), 3 * dx, f)
    assert std[0] == "standard" and conj[0] == "conjugate", (std, conj)
    assert std[1] > 10 and conj[1] < 0.1            # measured 72 and 0.014 (the other sign's misfit ratio)
    assert iq_convention(iq[0], iq[0], 3 * dx, f)[0] == "unknown"        # no motion: nothing to tell
    path = tmp_path / "conj.npz"
    np.savez(path, rf=np.conj(iq), spacing=(3 * dx, dy))
    with pytest.raises(OrientationError, match="--iq-conjugate") as err:
        read_frames(path, modulation_frequency=f)
    assert err.value.problem == "iq-sign"
    fr = read_frames(path, modulation_frequency=f, iq_conjugate=True)
    assert fr.metadata["iq"]["conjugate"] and fr.metadata["iq"]["convention_check"][0] == "standard"
    r = femreg.register(fr.frames[0], fr.frames[1], spacing=fr.spacing, origin=pair.origin)
    e = r.strain(r.pixel_points()[::7])[:, 0]
    # measured: axial strain RMS error 0.0007 of the 1 % with the sign put right (0.47 % mean strain without)
    assert np.sqrt(np.nanmean((e + 0.01) ** 2)) / 0.01 < 0.02
    # two single-frame files: the CLI checks the pair
    for k in range(2):
        np.save(tmp_path / f"c{k}.npy", np.conj(iq[k]))
    run = _cli(["register", tmp_path / "c0.npy", tmp_path / "c1.npy", "--spacing", f"{3 * dx}", f"{dy}",
                "--iq-frequency", f"{f}", "-o", tmp_path / "r.npz"], capsys)
    assert run.returncode == 2 and "--iq-conjugate" in run.stderr and "Traceback" not in run.stderr, run.stderr


def test_wrong_demodulation_frequency_is_refused(pair, tmp_path):
    from femreg.io.iq import iq_convention

    iq, dx, dy, f = _pair_iq(pair)
    v = iq_convention(iq[0], iq[1], 3 * dx, 1.2 * f)
    # a 20 % wrong frequency scaled the registered strain by 0.835 (success=True); the phases show the right one
    assert v[0] == "frequency" and abs(v[3] / f - 1) < 0.02, v          # measured 7.5 MHz for 7.5
    path = tmp_path / "iq.npz"
    np.savez(path, rf=iq, spacing=(3 * dx, dy))
    with pytest.raises(OrientationError, match="MHz demodulation") as err:
        read_frames(path, modulation_frequency=1.2 * f)
    assert err.value.problem == "iq-frequency"
    read_frames(path, modulation_frequency=1.2 * f, check_orientation=False)
    assert read_frames(path, modulation_frequency=f).metadata["iq"]["convention_check"][0] == "standard"
