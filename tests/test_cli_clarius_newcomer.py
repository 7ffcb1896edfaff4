"""A Clarius export on the command line, as a first-time user meets it: the lateral pitch typed in metres, as the
YAML settings state it, used to be refused by the echo finder as "the echo region -0.00 to 0.03 mm is too small
for a mesh" (nothing about the spacing); now it is refused as a spacing whose units are wrong, with the spacing the
settings imply.  A small simulated L12 pair (forward.pairs)."""
from __future__ import annotations

import numpy as np
import pytest

from femreg.cli import main

DX, DY = 0.01283, 0.1          # L12: 60 MHz sampling, 0.1 mm pitch


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    from forward import fields as F
    from forward.pairs import make_pair

    pr = make_pair(F.compression(0.01), "L12", (8.0, 6.4), 30.0, seed=3)
    frames = np.stack([pr.ref, pr.mov])
    counts = np.round(frames * 8000 / np.abs(frames).max()).astype("<i2")
    out = tmp_path_factory.mktemp("clarius") / "scan_rf.raw"
    blob = np.array([2, 2, counts.shape[2], counts.shape[1], 2], "<i4").tobytes()
    for k in range(2):
        blob += np.int64(k * 50_000_000).tobytes() + np.ascontiguousarray(counts[k].T).tobytes()
    out.write_bytes(blob)
    out.with_suffix(".yml").write_text("sampling rate: 60 MHz\nprobe:\n  pitch: 0.0001\n")
    return out


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_pitch_in_metres_is_refused_as_units_with_the_settings_spacing(scan, tmp_path, capsys):
    rc, _, err = _run(["register", scan, "-o", tmp_path / "p.npz", "--spacing", DX, 0.0001, "--no-progress"],
                      capsys)
    assert rc == 2, err
    assert "too small for a mesh" not in err and "units" in err, err
    assert "the 64 lines then span 0.0064 mm" in err, err
    assert "its fields suggest --spacing 0.01283 0.1" in err, err
    assert not (tmp_path / "p.npz").exists()
    # the spacing the settings imply passes the same check (info: described and ready)
    rc, out, err = _run(["info", scan, "--spacing", DX, DY], capsys)
    assert rc == 0 and "ready to register" in out, (out, err)
