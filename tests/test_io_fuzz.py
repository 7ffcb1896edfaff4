"""Property tests: truncated, random or corrupted bytes into every reader give a typed error (FileFormatError /
InputError, both ValueError subclasses) -- never another exception, never non-finite data.

Each property runs twice: a fixed, derandomised set of 60 inputs (default suite, the same every run) and a
randomised run of 1000 new inputs per property (``-m slow``; hypothesis prints the failing input to reproduce)."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from femreg.errors import InputError
from femreg.io import Frames, read_frames, save_frames

SP = (0.02, 0.2)
FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
RANDOM = settings(FUZZ, max_examples=1000, derandomize=False, database=None)
MODES = [pytest.param(FUZZ, id="fixed60"), pytest.param(RANDOM, id="random", marks=pytest.mark.slow)]

# name -> (file name, writer kwargs, reader kwargs); spacing is stored last where the format stores it, and the
# raw reader is given a 3D shape, so that *every* truncation is detectable.
FORMATS = {
    "npy": ("a.npy", {}, {"spacing": SP}),
    "npz": ("a.npz", {}, {}),
    "mat-v5": ("a.mat", {"mat_version": "5"}, {}),
    "mat-v7.3": ("a.mat", {"mat_version": "7.3"}, {}),
    "mhd-data": ("a.mhd", {}, {}),
    "mha": ("a.mha", {}, {}),
    "raw": ("a.raw", {}, {"shape": (2, 12, 6), "spacing": SP}),
    "rf": ("a.rf", {}, {"spacing": (None, 0.2)}),
    "rf-tags": ("a.rf", {"frame_tags": True}, {"spacing": (None, 0.2)}),
}


def _valid_bytes(tmp, name):
    fname, wkw, rkw = FORMATS[name]
    rng = np.random.default_rng(3)
    frames = np.rint(rng.standard_normal((2, 12, 6)) * 100).astype(np.float32)
    path = tmp / fname
    if name == "mat-v5":
        import scipy.io

        scipy.io.savemat(path, {"rf": np.moveaxis(frames, 0, -1), "spacing": np.array([SP])})
    else:
        save_frames(path, frames, SP, origin=None if fname.endswith((".mhd", ".mha")) else (0.0, 0.0), **wkw)
    # the file the fuzzer damages: the data file for .mhd, the file itself otherwise
    target = path.with_suffix(".raw") if name == "mhd-data" else path
    return path, target, target.read_bytes(), rkw


def _read_typed(path, rkw):
    """Read; return Frames or the typed error.  Anything else fails the test."""
    try:
        fr = read_frames(path, **rkw)
    except InputError as exc:  # FileFormatError is a subclass
        msg = str(exc)
        assert msg and "\n" not in msg, repr(msg)
        assert path.name in msg or "spacing" in msg or path.parent.name in msg, msg
        return exc
    assert isinstance(fr, Frames)
    assert np.all(np.isfinite(fr.frames))
    return fr


@pytest.mark.parametrize("fuzz", MODES)
@pytest.mark.parametrize("name", sorted(FORMATS))
def test_truncated_file_gives_typed_error(tmp_path_factory, name, fuzz):
    tmp = tmp_path_factory.mktemp(name)
    path, target, blob, rkw = _valid_bytes(tmp, name)
    assert isinstance(read_frames(path, **rkw), Frames)  # the intact file reads

    @fuzz
    @given(cut=st.integers(0, len(blob) - 1))
    def check(cut):
        target.write_bytes(blob[:cut])
        out = _read_typed(path, rkw)
        assert isinstance(out, InputError), f"{name} truncated to {cut} of {len(blob)} bytes read without error"

    check()


@pytest.mark.parametrize("fuzz", MODES)
@pytest.mark.parametrize("name", sorted(FORMATS))
def test_random_bytes_give_typed_error_or_valid_frames(tmp_path_factory, name, fuzz):
    tmp = tmp_path_factory.mktemp(name)
    path, target, blob, rkw = _valid_bytes(tmp, name)

    @fuzz
    @given(data=st.binary(min_size=0, max_size=3000))
    def check(data):
        target.write_bytes(data)
        _read_typed(path, rkw)

    check()


@pytest.mark.parametrize("fuzz", MODES)
@pytest.mark.parametrize("name", sorted(FORMATS))
def test_corrupted_bytes_give_typed_error_or_valid_frames(tmp_path_factory, name, fuzz):
    tmp = tmp_path_factory.mktemp(name)
    path, target, blob, rkw = _valid_bytes(tmp, name)
    n = len(blob)

    @fuzz
    @given(edits=st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8),
           head=st.booleans())
    def check(edits, head):
        b = bytearray(blob)
        for pos, val in edits:
            b[pos % 140 if head else pos] = val  # half of the cases hit the header region
        target.write_bytes(bytes(b))
        _read_typed(path, rkw)

    check()


@pytest.mark.parametrize("fuzz", MODES)
def test_random_metaimage_header_text(tmp_path_factory, fuzz):
    tmp = tmp_path_factory.mktemp("mhdtext")
    (tmp / "a.raw").write_bytes(b"\0" * 288)

    @fuzz
    @given(text=st.text(max_size=400))
    def check(text):
        (tmp / "a.mhd").write_text("NDims = 2\n" + text, encoding="utf-8", errors="surrogateescape")
        _read_typed(tmp / "a.mhd", {})

    check()
