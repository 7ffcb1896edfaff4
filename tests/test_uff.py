"""UFF (USTB's HDF5 format): beamformed frames of a linear scan read with their grid, IQ data remodulated to RF,
sector scans read and described but refused for registration.  The files are written here with h5py in USTB's
layout (MATLAB column-major: h5py sees every array with its axes reversed)."""
import h5py
import numpy as np
import pytest

from femreg.cli import main
from femreg.errors import FileFormatError, InputError
from femreg.io import read_frames
from femreg.synthetic import speckle_image


def _put(group, name, value):
    value = np.asarray(value)
    if np.iscomplexobj(value):
        g = group.create_group(name)
        g.create_dataset("real", data=value.real)
        g.create_dataset("imag", data=value.imag)
        g.attrs["complex"] = np.array([[1]], np.uint8)
        return g
    d = group.create_dataset(name, data=value)
    d.attrs["complex"] = np.array([[0]], np.uint8)
    return d


def write_uff(path, frames_zx, *, x_axis=None, z_axis=None, sector=None, f_mod=None, name="b_data",
              pixel_first=False):
    """frames (n, n_z, n_x) -> USTB beamformed data [pixel x 1 x 1 x frame] (h5py: (frame, 1, 1, pixel)),
    pixels depth-fastest."""
    n, nz, nx = frames_zx.shape
    with h5py.File(path, "w") as f:
        b = f.create_group(name)
        b.attrs["class"] = np.bytes_("uff.beamformed_data")
        s = b.create_group("scan")
        if sector is None:
            s.attrs["class"] = np.bytes_("uff.linear_scan")
            _put(s, "x_axis", np.asarray(x_axis)[None, :])
            _put(s, "z_axis", np.asarray(z_axis)[None, :])
        else:
            s.attrs["class"] = np.bytes_("uff.sector_scan")
            _put(s, "depth_axis", np.asarray(sector[0])[None, :])
            _put(s, "azimuth_axis", np.asarray(sector[1])[None, :])
        pix = frames_zx.transpose(0, 2, 1).reshape(n, nz * nx)          # depth fastest
        # as MATLAB writes it (h5py sees (frame, wave, channel, pixel)) or in USTB's own axis order
        _put(b, "data", pix.T[:, None, None, :] if pixel_first else pix[:, None, None, :])
        if f_mod is not None:
            _put(b, "modulation_frequency", np.array([[f_mod]]))
        _put(b, "sampling_frequency", np.array([[40e6]]))


@pytest.fixture(scope="module")
def rf():
    rng = np.random.default_rng(3)
    return np.stack([speckle_image((120, 24), (0.02, 0.2), rng) for _ in range(2)])


@pytest.mark.parametrize("pixel_first", [False, True])
def test_linear_scan_frames_grid_and_origin(rf, tmp_path, pixel_first):
    x = -2.3e-3 + 0.2e-3 * np.arange(rf.shape[2])
    z = 5e-3 + 0.02e-3 * np.arange(rf.shape[1])
    p = tmp_path / "lin.uff"
    write_uff(p, rf, x_axis=x, z_axis=z, pixel_first=pixel_first)
    fr = read_frames(p)
    assert fr.format == "uff" and fr.metadata["geometry"] == "linear"
    assert fr.frames.shape == rf.shape
    np.testing.assert_allclose(fr.frames, rf.astype(np.float32))       # axis order and pixel order kept
    np.testing.assert_allclose(fr.spacing, (0.02, 0.2))
    np.testing.assert_allclose(fr.origin, (5.0, -2.3))


def test_iq_is_remodulated_to_rf(tmp_path):
    # RF of a 5 MHz carrier with a smooth envelope, demodulated to IQ as USTB does: iq = rf exp(-2 pi i f t)
    # low-passed (here: the analytic signal, exact for a band-limited RF)
    from scipy.signal import hilbert

    c, f0 = 1540.0, 5e6
    z = 4e-3 + 0.01e-3 * np.arange(400)            # 10 um: 15 samples per RF period (c / 2 f0 = 154 um)
    env = np.exp(-((z - 6e-3) / 1e-3) ** 2)[:, None] * np.linspace(0.5, 1.5, 8)[None, :]
    rf = env * np.cos(2 * np.pi * f0 * 2 * z / c + 0.3)[:, None]
    iq = hilbert(rf, axis=0) * np.exp(-2j * np.pi * f0 * 2 * z / c)[:, None]
    p = tmp_path / "iq.uff"
    write_uff(p, iq[None], x_axis=0.3e-3 * np.arange(8), z_axis=z, f_mod=f0)
    fr = read_frames(p)
    assert fr.metadata["remodulated"] and fr.metadata["upsampled"] == 1
    err = np.abs(fr.frames[0] - rf).max() / np.abs(rf).max()
    assert err < 1e-3, err
    # a coarse grid (2 samples per period) is upsampled before remodulation
    p2 = tmp_path / "iq_coarse.uff"
    write_uff(p2, iq[None, ::8], x_axis=0.3e-3 * np.arange(8), z_axis=z[::8], f_mod=f0)
    fr2 = read_frames(p2)
    assert fr2.metadata["upsampled"] >= 2 and fr2.spacing[0] <= 0.154 / 4
    # IQ without a modulation frequency cannot be remodulated
    p3 = tmp_path / "iq_nofreq.uff"
    write_uff(p3, iq[None], x_axis=0.3e-3 * np.arange(8), z_axis=z)
    with pytest.raises(FileFormatError, match="modulation_frequency"):
        read_frames(p3)


def test_sector_scan_is_described_but_not_registered(rf, tmp_path, capsys):
    depth = 1e-3 + 0.02e-3 * np.arange(rf.shape[1])
    az = np.deg2rad(-6.0 + 0.5 * np.arange(rf.shape[2]))
    p = tmp_path / "sector.uff"
    write_uff(p, rf, sector=(depth, az))
    fr = read_frames(p)
    assert fr.metadata["geometry"] == "sector"
    np.testing.assert_allclose(fr.spacing, (0.02, 0.5))
    assert fr.metadata["scan"]["azimuth_deg"][2] == rf.shape[2]
    assert main(["info", str(p)]) == 0
    capsys.readouterr()
    assert main(["register", str(p), str(p), "-o", str(tmp_path / "r.npz")]) == 2
    assert "sector scan" in capsys.readouterr().err


def test_not_beamformed_data(tmp_path):
    p = tmp_path / "channels.uff"
    with h5py.File(p, "w") as f:
        f.create_group("channel_data").attrs["class"] = np.bytes_("uff.channel_data")
    with pytest.raises(FileFormatError, match="beamform"):
        read_frames(p)
    with pytest.raises((FileFormatError, InputError)):
        read_frames(tmp_path / "missing.uff")
