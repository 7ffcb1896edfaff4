"""Clarius research exports (``*_rf.raw`` + ``*_rf.yml``): layout, time stamps, settings, and refusals."""
import json

import numpy as np
import pytest

from femreg.cli import main
from femreg.errors import FileFormatError, InputError
from femreg.io import read_frames
from femreg.io.clarius import settings_fields, sniff

YML = """---
size:
  number of lines: 6
  samples per line: 40
  sample size: 2 bytes
type: rf
sampling rate: 40 MHz   # two-way: 0.01925 mm at 1540 m/s
probe:
  elements: 6
  pitch: 0.0003
frame rate: 20 Hz
"""


def _clarius(path, frames_ls, stamps=None, size=2, yml=YML):
    """Write ``frames_ls`` ((n, lines, samples)) as a Clarius raw file (and its YAML, unless None)."""
    frames_ls = np.asarray(frames_ls)
    n, nl, ns = frames_ls.shape
    stamps = np.arange(n, dtype="<i8") * 50_000_000 + 10**18 if stamps is None else stamps
    blob = np.array([2, n, nl, ns, size], "<i4").tobytes()
    for k in range(n):
        data = frames_ls[k].astype("<i2" if size == 2 else "u1")
        blob += np.int64(stamps[k]).astype("<i8").tobytes() + data.tobytes()
    path.write_bytes(blob)
    if yml is not None:
        path.with_suffix(".yml").write_text(yml)
    return path


def _coded(n=3, nl=6, ns=40):
    """Sample value 1000 k + 100 line + sample (line after line as stored)."""
    k, j, i = np.meshgrid(np.arange(n), np.arange(nl), np.arange(ns), indexing="ij")
    return 1000 * k + 100 * j + i


def test_layout_stamps_and_settings(tmp_path):
    p = _clarius(tmp_path / "scan_rf.raw", _coded())
    fr = read_frames(p, spacing=(0.01925, 0.3))
    assert fr.frames.shape == (3, 40, 6)        # (n, samples = axial, lines = lateral)
    k, i, j = np.meshgrid(np.arange(3), np.arange(40), np.arange(6), indexing="ij")
    np.testing.assert_array_equal(fr.frames, 1000 * k + 100 * j + i)
    assert fr.metadata["format"] == "clarius" and fr.metadata["stored_dtype"] == "int16"
    assert fr.metadata["frame_rate_hz"] == pytest.approx(20.0)
    assert fr.metadata["fields"]["sampling rate_MHz"] == 40.0
    assert fr.metadata["fields"]["probe/pitch"] == 0.0003
    np.testing.assert_array_equal(read_frames(p, spacing=(0.01925, 0.3), frames=[2, 0]).frames, fr.frames[[2, 0]])
    # no spacing given: refused, naming the one the settings imply (c / (2 fs), the pitch in mm)
    with pytest.raises(InputError, match=r"--spacing 0\.01925 0\.3"):
        read_frames(p)


def test_settings_nesting_units_and_comments(tmp_path):
    (tmp_path / "a_rf.yml").write_text(YML + "imaging depth: 4 cm\nlines:\n  - 1\n  - 2\nname: L15 HD\n")
    name, f = settings_fields(tmp_path / "a_rf.raw")
    assert name == "a_rf.yml"
    assert f == {"size/number of lines": 6, "size/samples per line": 40, "size/sample size_bytes": 2,
                 "sampling rate_MHz": 40, "probe/elements": 6, "probe/pitch": 0.0003, "frame rate_Hz": 20,
                 "imaging depth_cm": 4}
    assert settings_fields(tmp_path / "b_rf.raw") == (None, {})


def test_recognised_by_size_only(tmp_path):
    p = _clarius(tmp_path / "a_rf.raw", _coded(), yml=None)
    assert sniff(p) == {"id": 2, "frames": 3, "lines": 6, "samples": 40, "samplesize": 2}
    # headerless samples of the same length: a plain raw file, which needs --shape
    (tmp_path / "plain.raw").write_bytes(np.random.default_rng(0).integers(-999, 999, p.stat().st_size // 2,
                                                                           dtype="<i2").tobytes())
    assert sniff(tmp_path / "plain.raw") is None
    with pytest.raises(InputError, match="shape"):
        read_frames(tmp_path / "plain.raw", spacing=(0.02, 0.3))
    # a --shape or --dtype against the header's is refused, naming the header's
    with pytest.raises(InputError, match="40 samples x 6 lines"):
        read_frames(p, shape=(40, 5), spacing=(0.02, 0.3))
    with pytest.raises(InputError, match="int16"):
        read_frames(p, dtype="float32", spacing=(0.02, 0.3))
    np.testing.assert_array_equal(read_frames(p, shape=(40, 6), dtype="int16", spacing=(0.02, 0.3)).frames,
                                  read_frames(p, spacing=(0.02, 0.3)).frames)


def test_envelope_bytes(tmp_path):
    p = _clarius(tmp_path / "a_env.raw", _coded(2, 4, 30) % 250, size=1, yml=None)
    fr = read_frames(p, spacing=(0.02, 0.3))
    assert fr.metadata["stored_dtype"] == "uint8" and fr.frames.shape == (2, 30, 4)


def test_info_names_the_spacing_then_is_ready(tmp_path, capsys):
    rf = np.random.default_rng(1).standard_normal((2, 6, 40)) * 500
    p = _clarius(tmp_path / "scan_rf.raw", rf)
    assert main(["info", str(p), "--json"]) == 1
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "clarius" and info["frames"] == 2
    assert "--spacing 0.01925 0.3" in json.dumps(info)


def test_cut_short_and_headers_are_named(tmp_path):
    p = _clarius(tmp_path / "a_rf.raw", _coded(), yml=None)
    blob = p.read_bytes()
    # a copy cut short: the header's frames, and the whole frames the file holds
    (tmp_path / "cut_rf.raw").write_bytes(blob[:-5])
    assert sniff(tmp_path / "cut_rf.raw") is None
    with pytest.raises(FileFormatError, match=r"truncated Clarius raw export.*room for 2 whole frame"):
        read_frames(tmp_path / "cut_rf.raw", spacing=(0.02, 0.3))
    # a headered file read as headerless samples: the bytes over the whole frames are counted as a header
    (tmp_path / "h.raw").write_bytes(b"\1" * 36 + bytes(3 * 480) + b"\2" * 12)
    for shape in ((40, 6), (3, 40, 6)):
        with pytest.raises(FileFormatError, match=r"48 bytes over 3 whole frame\(s\), as a header"):
            read_frames(tmp_path / "h.raw", shape=shape, dtype="int16", spacing=(0.02, 0.3))


def test_unpacked_export_folder_names_the_files(tmp_path):
    # a Clarius export unpacked: the RF and envelope loops side by side (the folder reader took them for one frame
    # per file and stopped at "frame shape (40, 6) differs from a_env.raw's (30, 4)")
    _clarius(tmp_path / "a_rf.raw", _coded())
    _clarius(tmp_path / "a_env.raw", _coded(3, 4, 30) % 250, size=1, yml=None)
    with pytest.raises(FileFormatError, match=r"Clarius exports.*a_rf.raw: RF, 3 frame\(s\) of 40 x 6.*pass one "
                                              r"file, e\.g\. .*a_rf\.raw"):
        read_frames(tmp_path, spacing=(0.02, 0.3))
    (tmp_path / "a_env.raw").unlink()       # one loop alone in its folder reads as that file
    np.testing.assert_array_equal(read_frames(tmp_path, spacing=(0.02, 0.3)).frames,
                                  read_frames(tmp_path / "a_rf.raw", spacing=(0.02, 0.3)).frames)


def test_dtype_words_are_compared_as_types(tmp_path, capsys):
    rf = np.random.default_rng(1).standard_normal((2, 6, 40)) * 500
    p = _clarius(tmp_path / "scan_rf.raw", rf)
    # "short" is int16: the header's type, no note that it was ignored (there was one, comparing the words)
    assert main(["info", str(p), "--dtype", "short", "--spacing", "0.01925", "0.3"]) in (0, 1)
    assert "ignored" not in capsys.readouterr().err
    assert main(["info", str(p), "--dtype", "float32", "--spacing", "0.01925", "0.3"]) == 2
    assert "states int16 samples" in capsys.readouterr().err


def test_iq_export_is_named_and_refused(tmp_path):
    """An IQ export (header id 0) holds I and Q per depth: twice the RF frame's bytes; named, not misread."""
    n, nl, ns = 2, 6, 40
    blob = np.array([0, n, nl, ns, 2], "<i4").tobytes()
    for k in range(n):
        blob += np.int64(k).astype("<i8").tobytes() + np.zeros((nl, 2 * ns), "<i2").tobytes()
    p = tmp_path / "scan_iq.raw"
    p.write_bytes(blob)
    assert sniff(p)["iq"] is True
    with pytest.raises(InputError, match="Clarius IQ export .*export the RF data"):
        read_frames(p, spacing=(0.02, 0.3))
    assert main(["info", str(p)]) == 2
    # an RF export of the same sizes is not read as IQ
    q = _clarius(tmp_path / "scan_rf.raw", _coded(n, nl, ns))
    assert "iq" not in sniff(q)


def test_the_header_is_read_once(tmp_path, monkeypatch):
    # read_raw asked whether the file is a Clarius export and read_clarius read its header again: two reads of it
    # (and, for a file that is none, one more by the truncation check)
    import femreg.io.clarius as clarius

    reads = []
    header = clarius._header
    monkeypatch.setattr(clarius, "_header", lambda path: reads.append(path) or header(path))
    p = _clarius(tmp_path / "scan_rf.raw", _coded())
    assert read_frames(p, spacing=(0.01925, 0.3)).frames.shape == (3, 40, 6)
    assert len(reads) == 1, reads
    reads.clear()
    short = tmp_path / "short_rf.raw"
    short.write_bytes(p.read_bytes()[:-10])          # cut short: named, from the same single reading
    with pytest.raises(FileFormatError, match="truncated Clarius raw export"):
        read_frames(short, spacing=(0.01925, 0.3))
    assert len(reads) == 1, reads
