"""femreg.io readers and writers: round trips of every format, header parsing, typed errors, the real data."""
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

import femreg
from femreg.errors import FileFormatError, InputError
from femreg.io import (Frames, element_strains, export_result, load_result, nodal_average, read_frames,
                       save_frames, save_result, write_vtu, write_xdmf)
from femreg.io.ultrasonix import HEADER_FIELDS

SP = (0.0193, 0.3)
INVIVO = (Path(__file__).parents[1] / "../shared/data/invivo_rf").resolve()


@pytest.fixture
def rf3():
    rng = np.random.default_rng(7)
    return (rng.standard_normal((3, 24, 10)) * 1000).round().astype(np.float32)


# (extension, save_frames kwargs, read_frames kwargs, spacing stored in the file, origin stored)
CASES = {
    "npy": (".npy", {}, {"spacing": SP}, False, False),
    "npz": (".npz", {}, {}, True, True),
    "mat-v5": (".mat", {"mat_version": "5"}, {}, True, True),
    "mat-v7-compressed": (".mat", {"mat_version": "7"}, {}, True, True),
    "mat-v7.3": (".mat", {"mat_version": "7.3"}, {}, True, True),
    "mhd-little": (".mhd", {"byte_order": "little"}, {}, True, True),
    "mhd-big": (".mhd", {"byte_order": "big"}, {}, True, True),
    "mhd-int16-big": (".mhd", {"byte_order": "big", "dtype": "int16"}, {}, True, True),
    "mha-local": (".mha", {}, {}, True, True),
    "raw-f32-little": (".raw", {}, {"shape": (24, 10), "spacing": SP}, False, False),
    "raw-f32-big": (".raw", {"byte_order": "big"}, {"shape": (3, 24, 10), "spacing": SP, "byte_order": "big"},
                    False, False),
    "raw-int16": (".raw", {"dtype": "int16"}, {"shape": (24, 10), "dtype": "int16", "spacing": SP}, False, False),
    "rf": (".rf", {}, {"spacing": (None, SP[1])}, True, False),
    "rf-frame-tags": (".rf", {"frame_tags": True}, {"spacing": (None, SP[1])}, True, False),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("ndim", [3, 2])
def test_round_trip_every_format(tmp_path, rf3, case, ndim):
    ext, wkw, rkw, has_spacing, has_origin = CASES[case]
    data = rf3 if ndim == 3 else rf3[1]
    origin = (1.5, -2.25)
    if ndim == 2 and len(rkw.get("shape", ())) == 3:
        rkw = dict(rkw, shape=(1,) + tuple(rkw["shape"][1:]))
    path = tmp_path / f"seq{ext}"
    written = save_frames(path, data, SP, origin=origin, **wkw)
    assert all(Path(p).is_file() for p in written), written
    fr = read_frames(path, **rkw)
    assert isinstance(fr, Frames)
    expect = data if ndim == 3 else data[None]
    assert fr.frames.shape == expect.shape, (case, fr.frames.shape)
    assert fr.frames.dtype == np.float32
    np.testing.assert_array_equal(fr.frames, expect, err_msg=case)
    assert fr.spacing == pytest.approx(SP, rel=1e-6), (case, fr.spacing)
    if has_origin:
        assert fr.origin == pytest.approx(origin), (case, fr.origin)
    assert fr.source == path
    fr.save(tmp_path / "again.npz")  # Frames.save -> save_frames
    np.testing.assert_array_equal(read_frames(tmp_path / "again.npz").frames, expect)
    if has_spacing and case != "rf" and case != "rf-frame-tags":
        # spacing stored in the file: reading without spacing= gives it; spacing= overrides it
        assert read_frames(path, spacing=(0.5, 0.7)).spacing == (0.5, 0.7)


def test_float64_kept_and_ints_converted(tmp_path, rf3):
    save_frames(tmp_path / "d.npz", rf3.astype(np.float64), SP)
    assert read_frames(tmp_path / "d.npz").frames.dtype == np.float64
    save_frames(tmp_path / "i.npz", rf3.astype(np.int16), SP)
    fr = read_frames(tmp_path / "i.npz")
    assert fr.frames.dtype == np.float32
    np.testing.assert_array_equal(fr.frames, rf3)


def test_spacing_required_where_the_file_has_none(tmp_path, rf3):
    save_frames(tmp_path / "a.npy", rf3)
    with pytest.raises(InputError, match="spacing"):
        read_frames(tmp_path / "a.npy")
    save_frames(tmp_path / "b.npz", rf3)  # no spacing key
    with pytest.raises(InputError, match=r"b\.npz.*spacing"):
        read_frames(tmp_path / "b.npz")
    for bad in [(0.0, 0.2), (-1, 1), (np.nan, 1), (1,), "x"]:
        with pytest.raises(InputError):
            read_frames(tmp_path / "b.npz", spacing=bad)


# ---------------------------------------------------------------------------------------------- MetaImage

def _mhd(path, lines, data: bytes | None = None, data_name=None):
    text = "\n".join(lines) + "\n"
    path.write_bytes(text.encode())
    if data is not None:
        (path.parent / data_name).write_bytes(data)


def test_metaimage_axis_mapping_matches_invivo_layout(tmp_path):
    # DimSize = nx ny with x fastest: x = lateral (scan line), y = axial; as the in vivo set's 128 x 2000.
    n_lat, n_ax = 4, 6
    flat = np.arange(n_ax * n_lat, dtype="<f4")
    _mhd(tmp_path / "a.mhd", ["ObjectType = Image", "NDims = 2", f"DimSize = {n_lat} {n_ax}",
                              "ElementSpacing = 0.2 0.02", "Offset = 3 1", "ElementType = MET_FLOAT",
                              "ElementDataFile = a.raw"], flat.tobytes(), "a.raw")
    fr = read_frames(tmp_path / "a.mhd")
    np.testing.assert_array_equal(fr.frames[0], flat.reshape(n_ax, n_lat))  # == np.fromfile(...).reshape(ax, lat)
    assert fr.spacing == (0.02, 0.2)
    assert fr.origin == (1.0, 3.0)
    assert fr.metadata["header"]["DimSize"] == f"{n_lat} {n_ax}"


@pytest.mark.parametrize("etype,code", [("MET_FLOAT", "f4"), ("MET_DOUBLE", "f8"), ("MET_SHORT", "i2"),
                                        ("MET_USHORT", "u2"), ("MET_UCHAR", "u1"), ("MET_CHAR", "i1"),
                                        ("MET_INT", "i4"), ("MET_UINT", "u4")])
@pytest.mark.parametrize("msb_key", ["ElementByteOrderMSB", "BinaryDataByteOrderMSB"])
@pytest.mark.parametrize("msb", [False, True])
def test_metaimage_element_types_and_byte_order(tmp_path, etype, code, msb_key, msb):
    vals = (np.arange(3 * 5 * 2) % 100).reshape(3, 5, 2)
    dt = np.dtype((">" if msb else "<") + code)
    _mhd(tmp_path / "a.mhd", ["NDims = 3", "DimSize = 2 5 3", "ElementSpacing = 0.3 0.1 1",
                              f"{msb_key} = {msb}", f"ElementType = {etype}", "ElementDataFile = d.bin"],
         vals.astype(dt).tobytes(), "d.bin")
    fr = read_frames(tmp_path / "a.mhd")
    np.testing.assert_array_equal(fr.frames, vals)
    assert fr.frames.dtype == (np.float64 if code == "f8" else np.float32)


def test_metaimage_header_size_local_list_and_compressed(tmp_path):
    vals = np.arange(2 * 3 * 4, dtype="<i2").reshape(2, 3, 4)
    base = ["NDims = 3", "DimSize = 4 3 2", "ElementSpacing = 0.2 0.05 1", "ElementType = MET_SHORT"]
    # HeaderSize: skip a 16-byte preamble; -1: data at the end of the file; data in a sub-folder
    (tmp_path / "sub").mkdir()
    _mhd(tmp_path / "h.mhd", base + ["HeaderSize = 16", "ElementDataFile = sub/h.dat"],
         b"x" * 16 + vals.tobytes(), "sub/h.dat")
    _mhd(tmp_path / "e.mhd", base + ["HeaderSize = -1", "ElementDataFile = e.dat"], b"junk" + vals.tobytes(), "e.dat")
    text = ("\n".join(base + ["ElementDataFile = LOCAL"]) + "\n").encode()
    (tmp_path / "l.mha").write_bytes(text + vals.tobytes())
    _mhd(tmp_path / "list.mhd", base + ["ElementDataFile = LIST", "f0.raw", "f1.raw"])
    for k in range(2):
        (tmp_path / f"f{k}.raw").write_bytes(vals[k].tobytes())
    _mhd(tmp_path / "pat.mhd", base + ["ElementDataFile = f%d.raw 0 1 1"])
    comp = zlib.compress(vals.tobytes())
    _mhd(tmp_path / "c.mhd", base + ["CompressedData = True", f"CompressedDataSize = {len(comp)}",
                                     "ElementDataFile = c.zraw"], comp, "c.zraw")
    for name in ("h.mhd", "e.mhd", "l.mha", "list.mhd", "pat.mhd", "c.mhd"):
        fr = read_frames(tmp_path / name)
        np.testing.assert_array_equal(fr.frames, vals, err_msg=name)
        assert fr.spacing == (0.05, 0.2), name


@pytest.mark.parametrize("lines,data,match", [
    (["NDims = 2", "DimSize = 4 3", "ElementType = MET_FLOAT", "ElementDataFile = d.raw"], 4 * 11, "truncated"),
    (["NDims = 2", "DimSize = 4 3", "ElementType = MET_WHATEVER", "ElementDataFile = d.raw"], 48, "ElementType"),
    (["NDims = 2", "DimSize = 4 x", "ElementType = MET_FLOAT", "ElementDataFile = d.raw"], 48, "DimSize"),
    (["NDims = 4", "DimSize = 4 3 1 1", "ElementType = MET_FLOAT", "ElementDataFile = d.raw"], 48, "NDims"),
    (["NDims = 2", "DimSize = 4 3", "ElementType = MET_FLOAT"], 48, "ElementDataFile"),
    (["NDims = 2", "DimSize = 4 3", "ElementType = MET_FLOAT", "ElementDataFile = nope.raw"], 48, "not found"),
    (["NDims = 2", "DimSize = 4 3", "ElementSpacing = 0 1", "ElementType = MET_FLOAT", "ElementDataFile = d.raw"],
     48, "spacing"),
    (["hello world"], 0, "MetaImage"),
])
def test_metaimage_bad_headers_are_typed(tmp_path, lines, data, match):
    _mhd(tmp_path / "a.mhd", lines, b"\0" * data, "d.raw")
    with pytest.raises(FileFormatError, match=match) as exc:
        read_frames(tmp_path / "a.mhd", spacing=None)
    assert "a.mhd" in str(exc.value) or "d.raw" in str(exc.value)
    assert "\n" not in str(exc.value)


# ---------------------------------------------------------------------------------------------- MATLAB

def test_mat_v73_layout_is_matlab_compatible(tmp_path, rf3):
    import h5py

    path = tmp_path / "m.mat"
    save_frames(path, rf3, SP, mat_version="7.3")
    head = path.read_bytes()[:128]
    assert head.startswith(b"MATLAB 7.3 MAT-file") and head[124:128] == b"\x00\x02IM"
    with h5py.File(path, "r") as f:
        # MATLAB rf(axial, lateral, frame) = (24, 10, 3), stored transposed in HDF5
        assert f["rf"].shape == (3, 10, 24)
        assert f["rf"].attrs["MATLAB_class"] == b"single"
        np.testing.assert_array_equal(f["rf"][()].T, np.moveaxis(rf3, 0, -1))


def test_mat_v73_written_by_someone_else(tmp_path, rf3):
    """A plain HDF5 file as MATLAB would write it (no header, variable named `data`) is read by auto-choice."""
    import h5py

    path = tmp_path / "other.mat"
    with h5py.File(path, "w") as f:
        f["data"] = np.moveaxis(rf3, 0, -1).T.astype(np.float64)
        f["data"].attrs["MATLAB_class"] = np.bytes_("double")
        f["label"] = np.frombuffer(b"ab", dtype="u1").astype("u2").reshape(2, 1)
        f["label"].attrs["MATLAB_class"] = np.bytes_("char")
    fr = read_frames(path, spacing=SP)
    np.testing.assert_array_equal(fr.frames, rf3)
    assert fr.metadata["variable"] == "data"


def test_mat_variable_choice(tmp_path, rf3):
    import scipy.io

    p = tmp_path / "v.mat"
    scipy.io.savemat(p, {"echo": rf3[0], "note": "hi", "gain": np.array([[3.0]])})
    fr = read_frames(p, spacing=SP)  # the only 2D numeric variable
    np.testing.assert_array_equal(fr.frames[0], rf3[0])
    scipy.io.savemat(p, {"a": rf3[0], "b": rf3[1]})
    with pytest.raises(FileFormatError, match="several"):
        read_frames(p, spacing=SP)
    np.testing.assert_array_equal(read_frames(p, variable="b", spacing=SP).frames[0], rf3[1])
    with pytest.raises(FileFormatError, match="missing variable 'c'"):
        read_frames(p, variable="c", spacing=SP)
    scipy.io.savemat(p, {"note": "hi"})
    with pytest.raises(FileFormatError, match="no 2D/3D numeric"):
        read_frames(p, spacing=SP)
    scipy.io.savemat(p, {"rf": rf3[0] + 1j})          # complex: IQ, which needs its modulation frequency
    with pytest.raises(InputError, match="complex samples .* IQ data"):
        read_frames(p, spacing=SP)


# ---------------------------------------------------------------------------------------------- Ultrasonix

def _rf_file(path, frames_lw, *, tags=False, sf=40_000_000, **over):
    n, w, h = len(frames_lw), frames_lw[0].shape[0], frames_lw[0].shape[1]
    hdr = dict.fromkeys(HEADER_FIELDS, 0)
    hdr.update(type=16, frames=n, w=w, h=h, ss=16, sf=sf, ld=w, txf=5_000_000)
    hdr.update(over)
    blob = struct.pack("<19i", *(hdr[k] for k in HEADER_FIELDS))
    for k, fr in enumerate(frames_lw):
        if tags:
            blob += struct.pack("<i", 100 + k)
        blob += np.asarray(fr, dtype="<i2").tobytes()  # (w lines, h samples): column-major frame
    path.write_bytes(blob)


@pytest.mark.parametrize("tags", [False, True])
def test_ultrasonix_layout_header_and_tags(tmp_path, tags):
    w, h = 5, 12
    lines = [np.add.outer(np.arange(w) * 100 + k * 1000, np.arange(h)) for k in range(3)]  # value = 1000k+100j+i
    _rf_file(tmp_path / "a.rf", lines, tags=tags, sf=40_000_000)
    fr = read_frames(tmp_path / "a.rf", spacing=(None, 0.3))
    assert fr.frames.shape == (3, h, w)
    k, i, j = np.meshgrid(np.arange(3), np.arange(h), np.arange(w), indexing="ij")
    np.testing.assert_array_equal(fr.frames, 1000 * k + 100 * j + i)
    assert fr.spacing[0] == pytest.approx(1540e3 / (2 * 40e6)), fr.spacing
    assert fr.metadata["frame_tags"] is tags
    assert fr.metadata["header"]["sf"] == 40_000_000
    if tags:
        assert fr.metadata["frame_numbers"] == [100, 101, 102]
    assert read_frames(tmp_path / "a.rf", spacing=(None, 0.3), sound_speed=1500).spacing[0] == \
        pytest.approx(1500e3 / 80e6)
    # a given axial spacing 2.6 x c / (2 sf) contradicts the header: refused, unless the check is overridden
    with pytest.raises(InputError, match=r"file states 40 MHz .* c / \(2 fs\) is 0\.01925 mm"):
        read_frames(tmp_path / "a.rf", spacing=(0.05, 0.3))
    assert read_frames(tmp_path / "a.rf", spacing=(0.05, 0.3), check_orientation=False).spacing == (0.05, 0.3)
    np.testing.assert_array_equal(read_frames(tmp_path / "a.rf", spacing=(None, 0.3), frames=[2, 0]).frames,
                                  fr.frames[[2, 0]])


def test_ultrasonix_errors(tmp_path):
    lines = [np.zeros((4, 8))] * 2
    _rf_file(tmp_path / "a.rf", lines)
    with pytest.raises(InputError, match="lateral") as err:
        read_frames(tmp_path / "a.rf")
    # the header's half of the spacing is named: dx = c / (2 sf) = 1540 m/s / 80 MHz
    assert "its fields suggest --spacing 0.01925 DY" in str(err.value), err.value
    blob = (tmp_path / "a.rf").read_bytes()
    (tmp_path / "t.rf").write_bytes(blob[:-10])
    with pytest.raises(FileFormatError, match="truncated"):
        read_frames(tmp_path / "t.rf", spacing=(None, 0.3))
    (tmp_path / "x.rf").write_bytes(blob + b"\0" * 3)
    with pytest.raises(FileFormatError, match="size mismatch"):
        read_frames(tmp_path / "x.rf", spacing=(None, 0.3))
    _rf_file(tmp_path / "b.rf", lines, type=4)
    with pytest.raises(FileFormatError, match="type"):
        read_frames(tmp_path / "b.rf", spacing=(None, 0.3))
    _rf_file(tmp_path / "c.rf", lines, sf=0)
    with pytest.raises(FileFormatError, match="sf"):
        read_frames(tmp_path / "c.rf", spacing=(None, 0.3))
    (tmp_path / "h.rf").write_bytes(blob[:40])
    with pytest.raises(FileFormatError, match="header"):
        read_frames(tmp_path / "h.rf", spacing=(None, 0.3))


# ---------------------------------------------------------------------------------------------- raw, dirs

def test_raw_shape_dtype_and_size_checks(tmp_path, rf3):
    p = tmp_path / "a.raw"
    rf3.astype("<i2").tofile(p)
    with pytest.raises(InputError, match="shape"):
        read_frames(p, spacing=SP)
    with pytest.raises(FileFormatError, match="int16"):  # float32 default does not fit: hint names int16
        read_frames(p, shape=(24, 10), spacing=SP, dtype="float32")
    with pytest.raises(FileFormatError, match="size mismatch"):
        read_frames(p, shape=(2, 24, 10), dtype="int16", spacing=SP)
    with pytest.raises(InputError, match="dtype"):
        read_frames(p, shape=(24, 10), dtype="complex64", spacing=SP)
    with pytest.raises(InputError, match="byte_order"):
        read_frames(p, shape=(24, 10), dtype="int16", byte_order="middle", spacing=SP)
    fr = read_frames(p, shape=(24, 10), dtype="<i2", spacing=SP)
    np.testing.assert_array_equal(fr.frames, rf3)
    np.save(tmp_path / "n.raw", rf3)  # an .npy mislabelled as raw
    os.replace(tmp_path / "n.raw.npy", tmp_path / "n.raw")
    with pytest.raises(FileFormatError, match="npy"):
        read_frames(tmp_path / "n.raw", shape=(24, 10), spacing=SP)


def test_directory_of_frames_natural_order(tmp_path, rf3):
    d = tmp_path / "seq"
    d.mkdir()
    frames = np.stack([np.full((6, 4), k, np.float32) for k in range(12)])
    for k in range(12):
        frames[k].tofile(d / f"frame{k + 1}.raw")
    (d / "README").write_text("not a frame")
    fr = read_frames(d, shape=(6, 4), spacing=SP)
    np.testing.assert_array_equal(fr.frames[:, 0, 0], np.arange(12))  # frame10 after frame9, not after frame1
    assert fr.metadata["files"][9] == "frame10.raw"
    np.testing.assert_array_equal(read_frames(d, shape=(6, 4), spacing=SP, frames=slice(2, 5)).frames[:, 0, 0],
                                  [2, 3, 4])
    # a stop past the last frame is refused (it was cut short silently); no stop, or the end itself, is fine
    with pytest.raises(InputError, match="reaches past the last frame.*has 12"):
        read_frames(d, shape=(6, 4), spacing=SP, frames=slice(10, 40))
    assert read_frames(d, shape=(6, 4), spacing=SP, frames=slice(10, 12)).frames.shape[0] == 2
    assert read_frames(d, shape=(6, 4), spacing=SP, frames=slice(10, None)).frames.shape[0] == 2
    np.zeros((5, 4), np.float32).tofile(d / "frame13.raw")
    with pytest.raises(FileFormatError, match="frame13"):
        read_frames(d, shape=(6, 4), spacing=SP)
    (d / "frame13.raw").unlink()
    # femreg's own results written beside the frames (the README's first-recording steps) are set aside
    np.savez(d / "pair.npz", mesh_points=np.zeros((2, 4)), mesh_cells=np.zeros((4, 1), np.int64), u=np.zeros(8))
    fr = read_frames(d, shape=(6, 4), spacing=SP)
    assert fr.frames.shape[0] == 12 and fr.metadata["set_aside"] == ["pair.npz"]
    np.save(d / "x.npy", frames[0])
    with pytest.raises(FileFormatError, match=r"mixes formats \(npy: x.npy; raw: frame1.raw, frame2.raw"):
        read_frames(d, shape=(6, 4), spacing=SP)
    (d / "x.npy").unlink()
    np.savez(d / "frames.npz", rf=frames)  # an npz of frames is data, not a result: still a mix
    with pytest.raises(FileFormatError, match="mixes formats"):
        read_frames(d, shape=(6, 4), spacing=SP)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileFormatError, match="no frame files"):
        read_frames(tmp_path / "empty")
    os.replace(d / "pair.npz", tmp_path / "empty" / "pair.npz")  # a folder of results only: says so
    with pytest.raises(FileFormatError, match=r"1 femreg result file\(s\) set aside \(pair.npz\)"):
        read_frames(tmp_path / "empty")


# ---------------------------------------------------------------------------------------------- typed errors

def test_common_errors_are_typed_one_line(tmp_path, rf3):
    def err(path, **kw):
        with pytest.raises(InputError) as exc:
            read_frames(path, **kw)
        msg = str(exc.value)
        assert "\n" not in msg and str(Path(path).name) in msg, msg
        return msg

    assert "no such file" in err(tmp_path / "missing.npz")
    (tmp_path / "a.xyz").write_bytes(b"hello")
    assert "unknown file type" in err(tmp_path / "a.xyz")
    (tmp_path / "e.npy").write_bytes(b"")
    assert "empty" in err(tmp_path / "e.npy")
    nan = rf3.copy()
    nan[1, 2, 3] = np.nan
    save_frames(tmp_path / "nan.npz", nan, SP)
    assert "NaN" in err(tmp_path / "nan.npz")
    np.savez(tmp_path / "obj.npz", rf=np.array([{"a": 1}, None], dtype=object), spacing=np.array(SP))
    assert "object" in err(tmp_path / "obj.npz")  # never unpickled
    save_frames(tmp_path / "m.npz", rf3, SP)
    os.replace(tmp_path / "m.npz", tmp_path / "m.mat")
    assert "npz" in err(tmp_path / "m.mat")  # mislabelled: content says zip/npz
    np.save(tmp_path / "one.npy", np.zeros(5, np.float32))
    assert "dimension" in err(tmp_path / "one.npy", spacing=SP)
    np.save(tmp_path / "four.npy", np.zeros((2, 2, 2, 2), np.float32))
    assert "dimension" in err(tmp_path / "four.npy", spacing=SP)
    save_frames(tmp_path / "k.npz", rf3, SP, variable="echo")
    assert "'rf'" in err(tmp_path / "k.npz")
    np.testing.assert_array_equal(read_frames(tmp_path / "k.npz", variable="echo").frames, rf3)
    assert "out of range" in err(tmp_path / "k.npz", variable="echo", frames=5)


# ---------------------------------------------------------------------------------------------- real data

def test_read_invivo_sequence():
    seq = INVIVO / "seq299"
    if not seq.is_dir():
        pytest.skip(f"in vivo data not found at {INVIVO}")
    fr = read_frames(seq, shape=(2000, 128), spacing=(0.02, 0.2))
    assert fr.frames.shape == (6, 2000, 128)
    assert fr.spacing == (0.02, 0.2)
    for k in (0, 5):
        ref = np.fromfile(seq / f"frame{k + 1}.raw", "<f4").reshape(2000, 128)
        np.testing.assert_array_equal(fr.frames[k], ref)
    assert 0.5 < np.abs(fr.frames).max() < 2.0, np.abs(fr.frames).max()  # "normalised to about +-1"
    one = read_frames(seq / "frame3.raw", shape=(2000, 128), spacing=(0.02, 0.2))
    np.testing.assert_array_equal(one.frames[0], fr.frames[2])


def test_metaimage_header_for_invivo_frame_agrees(tmp_path):
    """A MetaImage header as the sequence's own (x = 128 lines, y = 2000 samples) gives the same frame and spacing."""
    raw = INVIVO / "seq304" / "frame2.raw"
    if not raw.is_file():
        pytest.skip(f"in vivo data not found at {INVIVO}")
    _mhd(tmp_path / "f.mhd", ["ObjectType = Image", "NDims = 2", "DimSize = 128 2000", "ElementSpacing = 0.2 0.02",
                              "ElementType = MET_FLOAT", "ElementByteOrderMSB = False", f"ElementDataFile = {raw}"])
    fr = read_frames(tmp_path / "f.mhd")
    assert fr.spacing == (0.02, 0.2) and fr.frames.shape == (1, 2000, 128)
    np.testing.assert_array_equal(fr.frames[0], np.fromfile(raw, "<f4").reshape(2000, 128))


# ---------------------------------------------------------------------------------------------- results

def _quad_mesh(nx=4, ny=3, skew=0.0):
    x, y = np.meshgrid(np.linspace(0, 2, nx + 1), np.linspace(0, 1.5, ny + 1), indexing="ij")
    x = x + skew * np.sin(3 * y) * x * (2 - x)  # curved, non-parallelogram quads
    p = np.vstack([x.ravel(), y.ravel()])
    idx = np.arange(p.shape[1]).reshape(nx + 1, ny + 1)
    t = np.vstack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()])
    return p, t


def _affine_u(p, A, b=(0.01, -0.02)):
    u = np.zeros(2 * p.shape[1])
    u[0::2] = A[0, 0] * p[0] + A[0, 1] * p[1] + b[0]
    u[1::2] = A[1, 0] * p[0] + A[1, 1] * p[1] + b[1]
    return u


def test_element_strains_exact_for_affine_field():
    p, t = _quad_mesh(skew=0.1)
    A = np.array([[0.004, 0.003], [-0.001, -0.002]])
    e = element_strains(p, t, _affine_u(p, A))
    expect = [A[0, 0], A[1, 1], 0.5 * (A[0, 1] + A[1, 0])]
    assert np.abs(e - expect).max() < 1e-14, np.abs(e - expect).max()
    en = nodal_average(t, e, p.shape[1])
    assert np.abs(en - expect).max() < 1e-14


@pytest.mark.parametrize("ext", [".vtu", ".xdmf"])
def test_vtu_xdmf_round_trip(tmp_path, ext):
    import meshio

    p, t = _quad_mesh()
    A = np.array([[0.004, 0.0], [0.002, -0.002]])
    u = _affine_u(p, A)
    writer = write_vtu if ext == ".vtu" else write_xdmf
    writer(tmp_path / f"r{ext}", p, t, u, cell_data={"id": np.arange(t.shape[1])})
    m = meshio.read(tmp_path / f"r{ext}")
    np.testing.assert_allclose(m.points[:, :2], p.T)
    assert m.cells[0].type == "quad"
    np.testing.assert_array_equal(m.cells[0].data, t.T)
    d = m.point_data["displacement"]
    assert d.shape == (p.shape[1], 3) and np.all(d[:, 2] == 0)
    np.testing.assert_allclose(d[:, 0], u[0::2])
    np.testing.assert_allclose(d[:, 1], u[1::2])
    np.testing.assert_allclose(m.cell_data["exx"][0], A[0, 0], atol=1e-15)
    np.testing.assert_allclose(m.cell_data["exy"][0], 0.001, atol=1e-15)
    np.testing.assert_allclose(m.point_data["eyy"], -0.002, atol=1e-15)
    np.testing.assert_array_equal(m.cell_data["id"][0], np.arange(t.shape[1]))


def _result(p, t, u, shape=(30, 20)):
    rng = np.random.default_rng(1)
    grid = {k: rng.standard_normal(shape) for k in ("ux", "uy", "exx", "eyy", "exy")}
    grid["ux"][:2] = np.nan
    return dict(mesh_points=p, mesh_cells=t, u=u, spacing=np.array([0.05, 0.075]), origin=np.zeros(2),
                shape=np.array(shape), regularizer="strain", alpha=0.5, success=True, nit=4, message="converged",
                ncc_before=0.3, ncc_after=0.9, energy_history=np.array([3.0, 2.0, 1.0]), **grid)


def test_result_npz_contract_round_trip_and_errors(tmp_path):
    p, t = _quad_mesh()
    u = _affine_u(p, np.eye(2) * 0.01)
    res = _result(p, t, u)
    save_result(tmp_path / "r.npz", res)
    back = load_result(tmp_path / "r.npz")            # the one reader: a RegistrationResult
    assert isinstance(back, femreg.RegistrationResult)
    assert back.regularizer == "strain" and back.success is True and back.nit == 4 and back.shape == (30, 20)
    np.testing.assert_array_equal(back.u, u)
    np.testing.assert_array_equal(back.on_grid()["ux"], res["ux"])
    np.testing.assert_array_equal(back.mesh.p, p)
    # written again from the object, read again: the same file contents (one writer, one reader)
    save_result(tmp_path / "r2", back)
    again = load_result(tmp_path / "r2.npz")
    np.testing.assert_array_equal(again.on_grid()["exx"], res["exx"])
    assert again.alpha == 0.5 and again.message == "converged" and again.ncc_after == 0.9
    export_result(tmp_path / "r.npz", tmp_path / "r.vtu")
    assert (tmp_path / "r.vtu").stat().st_size > 0
    bad = dict(res)
    del bad["u"]
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(FileFormatError, match="missing key.*u"):
        load_result(tmp_path / "bad.npz")
    bad = dict(res, u=u[:-1])
    np.savez(tmp_path / "bad2.npz", **bad)
    with pytest.raises(FileFormatError, match="u must be"):
        load_result(tmp_path / "bad2.npz")
    bad = dict(res, exx=res["exx"][:-1])
    np.savez(tmp_path / "bad3.npz", **bad)
    with pytest.raises(FileFormatError, match="exx.*shape"):
        load_result(tmp_path / "bad3.npz")
    bad = dict(res)
    del bad["spacing"]
    np.savez(tmp_path / "bad4.npz", **bad)
    with pytest.raises(FileFormatError, match="missing key.*spacing"):
        load_result(tmp_path / "bad4.npz")
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(FileFormatError, match="junk.npz"):
        load_result(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="vtu, .xdmf or .npz"):
        export_result(res, tmp_path / "r.obj")


def _mat5_element(order, mtype, payload: bytes, small_ok=True):
    if small_ok and len(payload) <= 4:
        return np.array([(len(payload) << 16) | mtype], order + "u4").tobytes() + payload.ljust(4, b"\0")
    head = np.array([mtype, len(payload)], order + "u4").tobytes()
    return head + payload + b"\0" * (-len(payload) % 8)


def _mat5_file(order, variables):
    """Hand-made Level-5 MAT-file with MATLAB's own tricks: small data elements for short names, and a
    double array stored as miUINT8 (MATLAB demotes integer-valued data)."""
    endian = b"IM" if order == "<" else b"MI"
    head = b"MATLAB 5.0 MAT-file, hand made".ljust(116, b" ") + b"\0" * 8
    head += np.array([0x0100], order + "u2").tobytes() + endian
    body = b""
    for name, arr, cls_id, mi_type, store in variables:
        flags = _mat5_element(order, 6, np.array([cls_id, 0], order + "u4").tobytes(), small_ok=False)
        dims = _mat5_element(order, 5, np.array(arr.shape, order + "i4").tobytes())
        nm = _mat5_element(order, 1, name.encode())
        real = _mat5_element(order, mi_type, np.asarray(arr, order + store).ravel(order="F").tobytes())
        body += _mat5_element(order, 14, flags + dims + nm + real, small_ok=False)
    return head + body


@pytest.mark.parametrize("order", ["<", ">"])
def test_mat5_reader_handles_matlab_storage_tricks(tmp_path, order):
    vals = np.arange(3 * 4 * 2).reshape(3, 4, 2) % 200  # MATLAB rf(axial=3, lateral=4, frame=2)
    blob = _mat5_file(order, [("rf", vals, 6, 2, "u1"),  # class double, stored as miUINT8
                              ("spacing", np.array([[0.05, 0.3]]), 6, 9, "f8")])
    (tmp_path / "h.mat").write_bytes(blob)
    fr = read_frames(tmp_path / "h.mat")
    np.testing.assert_array_equal(fr.frames, np.moveaxis(vals, -1, 0))
    assert fr.spacing == (0.05, 0.3)
    assert fr.metadata["format"] == "mat-v5"
    (tmp_path / "t.mat").write_bytes(blob[:-9])
    with pytest.raises(FileFormatError, match="truncated"):
        read_frames(tmp_path / "t.mat")


def test_ultrasonix_tagged_file_cut_to_the_untagged_size_is_truncated(tmp_path):
    """A tagged .rf file short by exactly 4 bytes per frame has the size of an untagged one; its frame numbers
    give it away (found by the randomised fuzzing run)."""
    frames = np.rint(np.random.default_rng(3).standard_normal((2, 12, 6)) * 100).astype(np.float32)
    save_frames(tmp_path / "a.rf", frames, (0.02, 0.2), origin=(0.0, 0.0), frame_tags=True)
    blob = (tmp_path / "a.rf").read_bytes()
    (tmp_path / "a.rf").write_bytes(blob[:-8])
    with pytest.raises(FileFormatError, match="truncated: frame tags present"):
        read_frames(tmp_path / "a.rf", spacing=(None, 0.2))
    save_frames(tmp_path / "b.rf", frames, (0.02, 0.2), origin=(0.0, 0.0))   # untagged, same size: reads
    np.testing.assert_array_equal(read_frames(tmp_path / "b.rf", spacing=(None, 0.2)).frames, frames)


def test_saved_grid_says_which_strain_it_holds(tmp_path):
    """Files record ``strain="recovered"``; a file marked ``strain="element"`` keeps its grid as the element grid
    and the default (recovered) grid is computed from the mesh and u."""
    from femreg.synthetic import speckle_pair

    spacing = (0.02, 0.1)
    ref, mov = speckle_pair(lambda p: np.c_[-0.01 * p[:, 0] + 0.001 * p[:, 1] ** 2, 0.004 * p[:, 1]],
                            shape=(300, 60), spacing=spacing, seed=5)
    res = femreg.register(ref, mov, spacing=spacing, element_size=(1.0, 1.0), maxiter=3)
    path = res.save(tmp_path / "new.npz")
    with np.load(path) as z:
        assert str(z["strain"]) == "recovered"
        old = {k: z[k] for k in z.files if k != "strain"}
    old["strain"] = "element"
    for k in ("exx", "eyy", "exy"):
        old[k] = res.on_grid("element")[k]
    np.savez(tmp_path / "old.npz", **old)
    new, older = load_result(path), load_result(tmp_path / "old.npz")
    for k in ("exx", "eyy", "exy"):
        np.testing.assert_array_equal(new.on_grid()[k], res.on_grid()[k])
        np.testing.assert_array_equal(older.on_grid("element")[k], res.on_grid("element")[k])
        np.testing.assert_allclose(older.on_grid()[k], res.on_grid()[k], atol=1e-14, equal_nan=True)
    assert np.nanmax(np.abs(res.on_grid()["exx"] - res.on_grid("element")["exx"])) > 1e-5


def test_mat_stack_written_frames_first_is_read_as_such(tmp_path):
    # scipy.io.savemat of an (n, axial, lateral) stack: MATLAB order would give 40 frames of 3 x 24 samples
    import scipy.io

    stack = np.random.default_rng(0).standard_normal((3, 24, 40)).astype(np.float32)
    scipy.io.savemat(tmp_path / "s.mat", {"rf": stack, "spacing": np.array([0.02, 0.2])})
    fr = read_frames(tmp_path / "s.mat")
    np.testing.assert_array_equal(fr.frames, stack)
    assert "frames first" in fr.metadata["layout"]
    scipy.io.savemat(tmp_path / "m.mat", {"rf": np.moveaxis(stack, 0, -1), "spacing": np.array([0.02, 0.2])})
    fr = read_frames(tmp_path / "m.mat")                       # the MATLAB order itself is unchanged
    np.testing.assert_array_equal(fr.frames, stack)
    assert "layout" not in fr.metadata
