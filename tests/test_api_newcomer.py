"""A first use of the Python library as README.md's Quick start shows it, on frames loaded as a user loads them
(``np.fromfile(...).reshape(2000, 128)``, float32 or int16), with a newcomer's mistakes: the spacing given
lateral first or as one number, the frames transposed or read from a raw file with their sizes exchanged, a NaN,
frames of different shapes, a stack of frames given to ``register``.  Small synthetic RF frames where they show
it; the in vivo recordings (tests skip without them) where only real data do."""
from pathlib import Path

import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.orientation import OrientationError

INVIVO = (Path(__file__).parents[1] / "../shared/data/invivo_rf").resolve()
SP = (0.02, 0.2)


def _rf(shape=(600, 96), lateral_sigma=4.0, seed=0):
    """An RF frame: a 4.6 MHz pulse along axis 0 at 0.02 mm (8.5 samples a period), speckle about 12 periods wide
    laterally at 0.2 mm a line (1.2 periods with 0.02 mm a line, as the in vivo seq304 read with square pixels)."""
    from scipy.ndimage import convolve1d, gaussian_filter1d

    t = np.arange(-20, 21)
    pulse = np.exp(-0.5 * (t / 4.0) ** 2) * np.cos(2 * np.pi * t / 8.5)
    noise = np.random.default_rng(seed).standard_normal(shape)
    return gaussian_filter1d(convolve1d(noise, pulse, axis=0), lateral_sigma, axis=1).astype(np.float32)


def _invivo(seq="seq304", k=(1, 2)):
    paths = [INVIVO / seq / f"frame{i}.raw" for i in k]
    if not all(p.is_file() for p in paths):
        pytest.skip(f"in vivo data not found under {INVIVO}")
    return [np.fromfile(p, "<f4").reshape(2000, 128) for p in paths]


# ----------------------------------------------------------------------------------------------- the spacing
def test_register_and_track_without_a_spacing_say_what_it_is():
    a = _rf()
    # before: TypeError "register() missing 1 required keyword-only argument: 'spacing'", a traceback
    with pytest.raises(InputError, match=r"spacing is required: \(dx, dy\) mm, the axial sample spacing"):
        femreg.register(a, a)
    with pytest.raises(InputError, match=r"spacing is required"):
        femreg.track([a, a])


def test_one_spacing_value_on_rf_frames_is_refused():
    from femreg.orientation import MIN_SQUARE_CELL_PERIODS, check, diagnose

    a = _rf()
    # square pixels: the lateral speckle 1.18 axial periods (above the 1 of the swapped-spacing check, below 2)
    rep = diagnose(a, (0.02, 0.02))
    assert not rep.problem and 1.0 < rep.cell_periods < MIN_SQUARE_CELL_PERIODS, rep.cell_periods
    # before: registered, success=True, every lateral distance 10 x too small
    with pytest.raises(OrientationError, match=r"spacing 0.02 \(one value\) means square pixels.*"
                                               r"spacing=\(0.02, DY\)"):
        femreg.register(a, a, spacing=0.02)
    with pytest.raises(OrientationError, match="one value"):
        femreg.track([a, _rf(seed=1)], spacing=0.02)
    assert check(a, SP, one_value=False).cell_periods > 10          # both values given: as before
    assert check(a, 0.02 * np.ones(2), one_value=False).problem == ""    # two equal values typed: not judged


@pytest.mark.parametrize("f0, beam_wavelengths", [(15.0, 1.5), (7.5, 1.5), (15.0, 3.0)])
def test_one_spacing_value_on_a_square_rf_grid_passes(f0, beam_wavelengths):
    # RF beamformed onto a square grid (a research scanner's plane-wave reconstruction) with a beam of 1.5
    # wavelengths (F-number about 1.5, near the diffraction limit): the lateral speckle spans 3.0 axial periods
    # (5.6 at 3 wavelengths), above the 2 of the one-value check, so the right square spacing is not refused
    pytest.importorskip("forward")
    from forward import fields as F
    from forward.pairs import Probe, make_pair
    from femreg.orientation import MIN_SQUARE_CELL_PERIODS, check

    pixel = 1.54 / (2 * 80.0 if f0 == 15.0 else 2 * 40.0)
    probe = Probe(f0, 80.0 if f0 == 15.0 else 40.0, pixel, beam_wavelengths * 1.54 / f0, name="square")
    d = make_pair(F.compression(0.01), probe, (4, 4), 30, 1, top_mm=5.0)
    rep = check(d.ref, (pixel, pixel), one_value=True)
    assert rep.cell_periods > 1.4 * MIN_SQUARE_CELL_PERIODS, rep.cell_periods


def test_one_spacing_value_on_the_invivo_frames_is_refused():
    f = _invivo()
    # seq304 with square pixels: lateral speckle 0.48 periods (seq299: 0.72; 1.2 and 0.96 before each envelope
    # row's mean was taken out, femreg.orientation._lateral_cell)
    with pytest.raises(OrientationError, match=r"one value\) means square pixels.*0.48 axial RF periods"):
        femreg.register(f[0], f[1], spacing=0.02)


def test_negative_spacing_is_named_in_plain_numbers():
    a = _rf()
    with pytest.raises(InputError) as info:
        femreg.register(a, a, spacing=(0.02, -0.2))
    # before: "got (np.float64(0.02), np.float64(-0.2))"
    assert str(info.value).endswith("got (0.02, -0.2)") and "np." not in str(info.value)


def test_swapped_spacing_and_transposed_frames_name_the_python_fix():
    a = _rf()
    with pytest.raises(OrientationError, match=r"look swapped: pass spacing \(0.02, 0.2\)"):
        femreg.register(a, a, spacing=(0.2, 0.02))
    with pytest.raises(OrientationError) as info:
        femreg.register(a.T, a.T, spacing=SP)
    # before: "transpose them (CLI: --transpose; frame.T, ... in Python)", the command line first
    assert "transpose them (frame.T, frames.transpose(0, 2, 1); read_frames(..., transpose=True); CLI: " \
           "--transpose)" in str(info.value), info.value


# ------------------------------------------------------------------------------------------------ the frames
def test_a_raw_file_read_with_its_sizes_exchanged_is_refused(tmp_path):
    from femreg.io import read_frames

    a = _rf((600, 80))
    a.tofile(tmp_path / "f.raw")
    # before: read as 80 x 600 without a word; registered as envelope data, success=True on scrambled frames
    with pytest.raises(OrientationError, match=r"the shape looks exchanged, pass shape=\(600, 80\) .*CLI: --shape "
                                               r"600 80"):
        read_frames(tmp_path / "f.raw", shape=(80, 600), spacing=SP)
    assert read_frames(tmp_path / "f.raw", shape=(80, 600), spacing=SP, check_orientation=False).shape == (80, 600)
    fr = read_frames(tmp_path / "f.raw", shape=(600, 80), spacing=SP)
    assert np.array_equal(fr.frames[0], a)


def test_a_stack_of_frames_given_to_register_is_named():
    stack = np.stack([_rf(), _rf(seed=1)])
    # before: "reference volume is too small: shape (2, 600, 96), need at least 4 voxels along every axis"
    with pytest.raises(InputError, match=r"a stack of frames\? register takes one frame each, register\(frames\[0\]"):
        femreg.register(stack, stack, spacing=SP)


def test_the_same_frame_twice_is_named():
    a = _rf()
    # before: 20 Gauss-Newton iterations at u = 0, "maximum number of iterations (20) reached", rows refined
    with pytest.raises(InputError, match=r"hold the same samples: nothing moved.*frames\[0\] and frames\[0\]"):
        femreg.register(a, a.copy(), spacing=SP)


def test_nan_and_frames_of_other_shapes_are_named():
    a, b = _rf(), _rf(seed=1)
    b[300, 40] = np.nan
    # before: "moving image has 1 NaN/Inf pixels (first at [300, 40])"
    with pytest.raises(InputError, match=r"moving image has NaN/Inf at 1 pixel \(first at \[300, 40\]\): every "
                                         r"sample must be finite"):
        femreg.register(a, b, spacing=SP)
    # before: "all frames must have the same shape, got [(590, 96), (600, 96)]", the frame unnamed
    with pytest.raises(InputError, match=r"frame 0 \(600, 96\), frame 2 \(590, 96\)$"):
        femreg.track([a, _rf(seed=2), a[:590]], spacing=SP)


def test_int16_and_float64_frames_give_the_same_answer():
    f = _invivo()
    i16 = [np.round(x / np.abs(x).max() * 30000).astype(np.int16) for x in f]
    r32 = femreg.register(f[0], f[1], spacing=SP)
    r16 = femreg.register(i16[0], i16[1], spacing=SP)
    r64 = femreg.register(f[0].astype(np.float64), f[1].astype(np.float64), spacing=SP)
    # measured: int16 counts 5.4e-6 mm from float32 (the rounding), float64 identical
    assert r32.success and np.nanmax(np.abs(r16.u - r32.u)) < 5e-5 and np.array_equal(r64.u, r32.u)


# ------------------------------------------------------------------------------------------------ the pictures
def test_plot_docs_say_what_each_function_returns_and_takes():
    import inspect

    import matplotlib.pyplot as plt

    import femreg.plot as P

    # before: "Every plot_* function takes ax= ... and returns the Axes": plot_result and plot_inversion take no
    # ax= and return the Figure
    assert "Every ``plot_*`` function" not in P.__doc__
    for name in ("plot_bmode", "plot_field", "plot_mesh_values", "plot_quality"):
        assert "ax" in inspect.signature(getattr(P, name)).parameters, name
    a = _rf((200, 40))
    res = femreg.register(a, np.roll(a, 1, axis=0), spacing=SP, initial="zero", roi=None, refine=None, maxiter=1)
    fig = P.plot_result(res, None, dpi=30)
    assert isinstance(fig, plt.Figure)
    plt.close(fig)
    e = res.strain(res.pixel_points())[:, 0]
    # before: "field must be a 2D (axial, lateral) array, got shape (8000,)", nothing on how to get one
    with pytest.raises(InputError, match=r"res.on_grid\(\)\['exx'\] or values.reshape\(res.shape\)"):
        P.plot_field(e, SP)
    ax = P.plot_field(e.reshape(res.shape), SP)
    plt.close(ax.figure)


def test_a_result_file_read_by_the_other_loader_names_the_right_one(tmp_path):
    from femreg.errors import FileFormatError
    from femreg.inversion import _FORMAT

    np.savez(tmp_path / "mu.npz", format=np.array(_FORMAT), meta=np.array("{}"))
    # before: "not a femreg result: missing key(s) u, spacing, origin, shape"
    with pytest.raises(FileFormatError, match="a shear-modulus image, not a registration result: read it with "
                                              "femreg.load_inversion"):
        femreg.load_result(tmp_path / "mu.npz")
    np.savez(tmp_path / "pair.npz", u=np.zeros(8), mesh_points=np.zeros((2, 4)), spacing=np.array(SP))
    # before: "not a femreg inversion file"
    with pytest.raises(FileFormatError, match="a registration result, read by femreg.load_result"):
        femreg.load_inversion(tmp_path / "pair.npz")
