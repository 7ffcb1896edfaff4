"""The io layers after the split: Frames.save writes through femreg.io.writers and every reader gives a Frames
back (the format modules return its fields); femreg.io.load_result is femreg.load_result."""
import numpy as np
import pytest

import femreg
import femreg.io as fio
from femreg.io.frames import Frames, finalize


@pytest.mark.parametrize("ext", ["npz", "mat", "mhd", "npy"])
def test_frames_save_and_read_back(tmp_path, ext):
    rng = np.random.default_rng(2)
    fr = finalize("x.npy", rng.standard_normal((2, 20, 8)).astype(np.float32), (0.1, 0.2), origin=(1.5, -2.0))
    written = fr.save(tmp_path / f"a.{ext}")
    back = fio.read_frames(written[0], spacing=(0.1, 0.2) if ext == "npy" else None)
    assert isinstance(back, Frames) and np.array_equal(back.frames, fr.frames)
    assert back.spacing == (0.1, 0.2)
    if ext != "npy":                                          # .npy stores no origin
        assert back.origin == (1.5, -2.0)


def test_format_readers_return_the_fields_of_a_frames(tmp_path):
    from femreg.io.metaimage import read_metaimage

    fr = finalize("x.npy", np.ones((1, 6, 5), np.float32), (0.05, 0.3))
    path = fr.save(tmp_path / "a.mhd")[0]
    fields = read_metaimage(path)
    assert isinstance(fields, dict) and set(fields) == {"frames", "spacing", "origin", "metadata", "source"}
    assert np.array_equal(Frames(**fields).frames, fr.frames)


def test_io_load_result_is_the_package_reader():
    assert fio.load_result is femreg.load_result
