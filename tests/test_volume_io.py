"""Volume readers: round trips through every format, the axis layout of each format written by hand, ambiguous
and bad input refused with a message naming the right reader, ``femreg info`` on volumes."""
import json

import numpy as np
import pytest

from femreg.errors import FileFormatError, InputError
from femreg.io import read_frames, read_volumes, save_volumes

SP = (0.025, 0.2, 0.3)
OR = (2.0, -3.0, -1.5)


def _vol(shape=(7, 5, 3)):
    """Distinct values telling every axis apart: v[i, j, k] = 10000 i + 100 j + k."""
    i, j, k = np.indices(shape)
    return (10000 * i + 100 * j + k).astype(np.float32)


@pytest.mark.parametrize("ext,kw", [(".npz", {}), (".mat", {"mat_version": "5"}), (".mat", {"mat_version": "7.3"}),
                                    (".mhd", {}), (".mha", {})])
def test_round_trip_volume_and_sequence(tmp_path, ext, kw):
    one = _vol()
    seq = np.stack([one, one + 0.5, one + 1.0])
    for name, arr in (("one", one), ("seq", seq)):
        path = tmp_path / f"{name}{ext}"
        save_volumes(path, arr, SP, origin=OR, **kw)
        v = read_volumes(path)
        want = arr[None] if arr.ndim == 3 else arr
        assert v.frames.shape == want.shape and np.array_equal(v.frames, want), (ext, name)
        assert v.spacing == pytest.approx(SP) and v.origin == pytest.approx(OR)
        assert v.shape == (7, 5, 3) and v.n_frames == len(want)
    assert read_volumes(tmp_path / f"seq{ext}", frames=[2]).frames[0][1, 2, 1] == pytest.approx(10201 + 1.0)


def test_npy_needs_spacing(tmp_path):
    p = tmp_path / "v.npy"
    np.save(p, _vol())
    with pytest.raises(InputError, match=r"spacing unknown.*\(dx, dy, dz\)"):
        read_volumes(p)
    v = read_volumes(p, spacing=SP)
    assert v.spacing == SP and np.array_equal(v[0], _vol())


def test_metaimage_axis_mapping_written_by_hand(tmp_path):
    """A header written here: MetaImage x = lateral (fastest), y = axial, z = elevational, the 4th axis the
    frame; spacing listed (dy, dx, dz)."""
    vol = np.stack([_vol(), _vol() + 1])                          # (2, 7, 5, 3)
    raw = np.ascontiguousarray(vol.transpose(0, 3, 1, 2))          # frame, elevational, axial, lateral (x fastest)
    raw.astype("<f4").tofile(tmp_path / "s.raw")
    (tmp_path / "s.mhd").write_text("ObjectType = Image\nNDims = 4\nDimSize = 5 7 3 2\nElementType = MET_FLOAT\n"
                                    "ElementSpacing = 0.2 0.025 0.3 1\nOffset = -3 2 -1.5 0\n"
                                    "ElementDataFile = s.raw\n")
    v = read_volumes(tmp_path / "s.mhd")
    assert np.array_equal(v.frames, vol)
    assert v.spacing == pytest.approx(SP) and v.origin == pytest.approx(OR)
    with pytest.raises(FileFormatError, match="read_volumes"):
        read_frames(tmp_path / "s.mhd")


def test_matlab_layout_frames_last(tmp_path):
    """MATLAB order rf(axial, lateral, elevational, frame), written by scipy directly."""
    import scipy.io

    vol = np.stack([_vol(), _vol() + 1])
    scipy.io.savemat(tmp_path / "m.mat", {"rf": np.moveaxis(vol, 0, -1), "spacing": np.array([SP])})
    v = read_volumes(tmp_path / "m.mat")
    assert np.array_equal(v.frames, vol) and v.spacing == pytest.approx(SP)


def test_ambiguous_and_bad_input(tmp_path):
    vol = _vol()
    # 2D frames (two spacing values) are not a volume, and a volume's three values are not 2D frames
    np.savez(tmp_path / "f2.npz", rf=vol, spacing=np.array([0.025, 0.2]))
    with pytest.raises(FileFormatError, match="read_frames"):
        read_volumes(tmp_path / "f2.npz")
    assert read_frames(tmp_path / "f2.npz").n_frames == 7          # the 2D reading is unchanged
    np.savez(tmp_path / "v3.npz", rf=vol, spacing=np.array(SP))
    with pytest.raises(FileFormatError, match="read_volumes"):
        read_frames(tmp_path / "v3.npz")
    np.savez(tmp_path / "s4.npz", rf=np.stack([vol, vol]), spacing=np.array([0.025, 0.2]))
    with pytest.raises(FileFormatError, match="read_volumes"):
        read_frames(tmp_path / "s4.npz", spacing=(0.025, 0.2))
    with pytest.raises(InputError, match="three numbers"):
        read_volumes(tmp_path / "v3.npz", spacing=(0.1, 0.2))
    np.savez(tmp_path / "d5.npz", rf=np.zeros((2, 3, 4, 5, 6)), spacing=np.array(SP))
    with pytest.raises(FileFormatError, match="5 dimension"):
        read_volumes(tmp_path / "d5.npz")
    np.savez(tmp_path / "flat.npz", rf=np.zeros((8, 6, 1)), spacing=np.array(SP))
    with pytest.raises(FileFormatError, match="degenerate"):
        read_volumes(tmp_path / "flat.npz")
    bad = vol.copy()
    bad[1, 1, 1] = np.nan
    np.savez(tmp_path / "nan.npz", rf=bad, spacing=np.array(SP))
    with pytest.raises(FileFormatError, match="NaN"):
        read_volumes(tmp_path / "nan.npz")
    (tmp_path / "x.rf").write_bytes(b"\0" * 100)
    with pytest.raises(InputError, match="volumes are read from"):
        read_volumes(tmp_path / "x.rf")


def test_cli_info_describes_volumes(tmp_path, capsys):
    from femreg.cli import main

    def _info(*args):
        rc = main(["info", *map(str, args)])
        cap = capsys.readouterr()
        return rc, cap.out, cap.err

    from forward.volume import Affine3D, VolumeProbe, make_volume_pair

    pair = make_volume_pair(Affine3D(0.01), VolumeProbe(7.0, 30.8, 0.2, 0.25, 0.9, 2.0), (3.0, 3.0, 2.0),
                            seed=0, snr_db=None)
    save_volumes(tmp_path / "pair.npz", pair.frames, pair.spacing, origin=pair.origin)
    rc, out, err = _info(tmp_path / "pair.npz", "--json")        # three spacing values: read as volumes unasked
    assert rc == 0, (out, err)
    info = json.loads(out)
    assert info["kind"] == "volume" and info["frames"] == 2 and info["shape"] == list(pair.ref.shape)
    assert info["spacing_mm"] == pytest.approx(list(pair.spacing))
    import re

    f_mhz = float(re.search(r"([\d.]+) MHz", info["rf_check"]).group(1))  # the 7 MHz carrier found on axis 0
    assert abs(f_mhz - 7.0) < 0.35, info["rf_check"]
    rc, out, _ = _info(tmp_path / "pair.npz")
    assert "elevational" in out and "volumes   2" in out
    np.save(tmp_path / "v.npy", pair.ref)                         # 3D array: 2D frames unless --volume
    rc, out, _ = _info(tmp_path / "v.npy", "--volume")
    assert rc == 1 and "no spacing found" in out


def _scanner_mat73(path, vols, fs_hz, pitch_m, elevation_m):
    """``vols`` (n, axial, lateral, elevational) as MATLAB's ``save -v7.3`` stores ``rf(sample, line, plane,
    volume)`` int16 beside its scanner's fields in SI units, with no spacing variable."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:       # MATLAB's HDF5 holds the reversed index order
        f["rf"] = np.ascontiguousarray(np.round(vols * 1000).astype(np.int16).transpose(0, 3, 2, 1))
        f["fs"] = np.array([[fs_hz]])
        f["pitch"] = np.array([[pitch_m]])
        f["elevation_pitch"] = np.array([[elevation_m]])
    with open(path, "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, HDF5 schema 1.00 .".ljust(116) + b"\x00" * 8 + b"\x00\x02IM")


def test_cli_volume_file_without_spacing(tmp_path, capsys, monkeypatch):
    """A scanner's 4D MAT-file without a spacing variable: info describes it as volumes without --volume and names
    the --spacing DX DY DZ its fields imply; register takes three --spacing values (before: info refused it
    naming femreg.io.read_volumes, and --spacing took two values while the error asked for three)."""
    from femreg.cli import main
    from femreg.volume_result import load_volume_result
    from forward.volume import Affine3D, make_volume_pair

    pair = make_volume_pair(Affine3D(0.01), "matrix7", (6.0, 6.0, 5.0), seed=0, snr_db=30.0)
    path = tmp_path / "scan.mat"
    _scanner_mat73(path, pair.frames / np.abs(pair.frames).max() * 30, 30.8e6, 0.2e-3, 0.25e-3)
    assert main(["info", str(path)]) == 1
    out = capsys.readouterr().out
    assert "(volumes)" in out and "volumes   2" in out
    assert "its fields suggest --spacing 0.025 0.2 0.25" in out, out
    assert main(["info", str(path), "--spacing", "0.025", "0.2", "0.25"]) == 0
    assert "0.25 mm elevational" in capsys.readouterr().out
    out_npz = tmp_path / "r.npz"
    assert main(["register", str(path), "-o", str(out_npz), "--spacing", "0.025", "0.2", "0.25"]) == 0
    line = capsys.readouterr().out.splitlines()[0]      # the frames' summary line, not the library's repr
    assert line.startswith("pair: ncc ") and " nodes, regularizer momentum-stress" in line, line
    res = load_volume_result(out_npz)
    assert res.spacing == pytest.approx((0.025, 0.2, 0.25)) and res.success
    # the result drawn: three slices of u_x, e_xx, e_yy, e_zz and the quality (before: refused, pointing to Python)
    png = tmp_path / "r.png"
    assert main(["plot", str(out_npz), "-o", str(png), "--slice", "4", "3", "2"]) == 0 and png.stat().st_size > 0
    # the figure's title names the voxel each panel shows, not the point typed (3.9 typed, 3.8 drawn before)
    import re

    import femreg.volplot as volplot
    figs = []
    draw = volplot.plot_volume_slices
    monkeypatch.setattr(volplot, "plot_volume_slices", lambda *a, **k: figs.append(draw(*a, **k)) or figs[-1])
    for typed in ((4.03, 3.07, 2.13), (3.91, 2.96, 2.37)):
        assert main(["plot", str(out_npz), "-o", str(png), "--slice", *map(str, typed)]) == 0
        fig = figs[-1]
        said = dict(zip("xyz", re.search(r"x, y, z = ([-\d.]+), ([-\d.]+), ([-\d.]+) mm", fig._suptitle.get_text())
                        .groups()))
        shown = {m.group(1): m.group(2) for ax in fig.axes
                 for m in [re.search(r"\b([xyz]) = ([-\d.]+) mm", ax.get_title())] if m}
        assert shown and all(said[a] == v for a, v in shown.items()), (said, shown)
    assert main(["plot", str(out_npz), "-o", str(png), "--slice", "4", "0"]) == 2
    assert "takes X Y Z" in capsys.readouterr().err
    # an axial spacing twice c / (2 fs) of the file's fs (the frames' check, now on volumes): before, registered
    assert main(["register", str(path), "-o", str(out_npz), "--spacing", "0.05", "0.2", "0.25"]) == 2
    assert "pass --spacing 0.025 0.2 0.25 (axial, lateral, elevational mm)" in capsys.readouterr().err
    assert main(["register", str(path), "-o", str(out_npz), "--spacing", "0.025", "0.2"]) == 2
    assert "volumes take --spacing DX DY DZ" in capsys.readouterr().err
    # elastogram takes frames: said before it asks for a spacing (before: the spacing, then "4 dimension(s)")
    assert main(["elastogram", str(path), "-o", str(tmp_path / "el")]) == 2
    assert "holds RF volumes" in capsys.readouterr().err
    np.save(tmp_path / "frames.npy", pair.ref[:, :, :2].transpose(2, 0, 1))      # two frames
    assert main(["info", str(tmp_path / "frames.npy"), "--spacing", "0.025", "0.2", "0.25"]) == 2
    assert "three values (DX DY DZ) is for RF volumes" in capsys.readouterr().err


def test_cli_failed_volume_names_the_exchanged_spacing(tmp_path, capsys):
    """Lateral and elevational spacings typed the other way round: nothing in the RF tells them apart, so a failed
    volume registration names the exchanged order (here 5 mm of elevation read as 4 mm is one element across, and
    the registration fails); spacings within 10 % of each other get no such hint."""
    from femreg.cli import main
    from femreg.cli._volume import _exchanged_hint
    from forward.volume import Affine3D, make_volume_pair

    pair = make_volume_pair(Affine3D(0.01), "matrix7", (6.0, 6.0, 5.0), seed=0, snr_db=30.0)
    path = tmp_path / "scan.mat"
    _scanner_mat73(path, pair.frames / np.abs(pair.frames).max() * 30, 30.8e6, 0.2e-3, 0.25e-3)
    assert main(["register", str(path), "-o", str(tmp_path / "r.npz"), "--spacing", "0.025", "0.25", "0.2",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "failed its checks" in err and "exchanged" in err and "--spacing 0.025 0.2 0.25" in err, err
    assert _exchanged_hint((0.025, 0.2, 0.21)) == "" and "--spacing 0.1 0.3 0.2" in _exchanged_hint((0.1, 0.2, 0.3))
