"""MATLAB v7.3 exports keep the scanner's settings in structs (Verasonics-style ``P.fs``, ``P.Trans.radiusMm``):
the reader lists their numbers by path, as it does a v5 file's, so `femreg info` names the spacing and the
convex geometry they imply."""
import math

import h5py
import numpy as np
import pytest


def _num(group, name, value, cls="double"):
    d = group.create_dataset(name, data=np.atleast_2d(np.asarray(value, float)).T)
    d.attrs["MATLAB_class"] = np.bytes_(cls)


@pytest.fixture
def export(tmp_path):
    """RFData(sample, line, frame) int16 with the settings in struct P and its nested struct P.Trans."""
    rng = np.random.default_rng(0)
    rf = np.round(rng.standard_normal((3, 40, 300)) * 500).astype(np.int16)     # HDF5: (frame, line, sample)
    path = tmp_path / "scan.mat"
    with h5py.File(path, "w", userblock_size=512) as f:
        ds = f.create_dataset("RFData", data=rf)
        ds.attrs["MATLAB_class"] = np.bytes_("int16")
        p = f.create_group("P")
        p.attrs["MATLAB_class"] = np.bytes_("struct")
        _num(p, "fs", 20.83e6)
        _num(p, "c", 1540.0)
        _num(p, "theta", ((np.arange(40) - 19.5) * math.radians(0.5))[None, :])
        t = p.create_group("Trans")
        t.attrs["MATLAB_class"] = np.bytes_("struct")
        _num(t, "radiusMm", 49.57)
        # a struct array's fields are object references: not numbers, left out
        t.create_dataset("refs", (1, 1), dtype=h5py.ref_dtype)
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, HDF5 schema 1.00 .".ljust(116) + b"\x00" * 8 + b"\x00\x02IM")
    return path


def test_struct_fields_read_by_path(export):
    from femreg.io import read_frames

    fr = read_frames(export, spacing=(0.037, 0.5))
    assert fr.frames.shape == (3, 300, 40)
    fields = fr.metadata["fields"]
    assert fields["P/fs"] == pytest.approx(20.83e6) and fields["P/c"] == 1540.0
    assert fields["P/Trans/radiusMm"] == pytest.approx(49.57)
    assert "P/Trans/refs" not in fields
    assert fr.metadata["axes"]["P/theta"]["n"] == 40


def test_info_names_spacing_and_geometry_from_structs(export, capsys):
    from femreg.cli import main

    rc = main(["info", str(export)])
    out = capsys.readouterr().out
    assert rc == 1
    dr = 1540.0 / (2 * 20.83e6) * 1e3
    assert f"--spacing {dr:.4g} auto" in out, out
    assert "--geometry convex --radius 49.57 --angle-pitch 0.5" in out, out


def test_info_takes_the_suggested_range_step(export, capsys):
    # the spacing info suggests for a convex file, --spacing DX auto, given back: the range step is complete (the
    # rays are --angle-pitch apart); only the geometry flags are still needed (before: "spacing incomplete: pass
    # both values", suggesting the very flag given)
    from femreg.cli import main

    dr = f"{1540.0 / (2 * 20.83e6) * 1e3:.4g}"
    rc = main(["info", str(export), "--spacing", dr, "auto"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "incomplete" not in out and f"spacing   {dr} mm range step (given)" in out, out
    needs = [line for line in out.splitlines() if line.startswith("needs")]
    assert len(needs) == 1 and "--geometry convex --radius 49.57 --angle-pitch 0.5" in needs[0], needs
