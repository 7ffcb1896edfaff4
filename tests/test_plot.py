"""femreg.plot: B-mode, fields with colour bars and mm axes, the result summary, the pyvista render."""
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from femreg.errors import InputError  # noqa: E402
from femreg.plot import bmode, extent_mm, plot_bmode, plot_field, plot_result, render_mesh  # noqa: E402

from test_io import _affine_u, _quad_mesh, _result  # noqa: E402


def _rf(shape=(200, 16), seed=0):
    rng = np.random.default_rng(seed)
    i = np.arange(shape[0])[:, None]
    return rng.standard_normal(shape) * np.sin(2 * np.pi * 0.1 * i)


def test_bmode_range_and_envelope():
    rf = _rf()
    b = bmode(rf, dynamic_range=40)
    assert b.shape == rf.shape
    assert b.max() == 0.0 and b.min() >= -40, (b.min(), b.max())
    # envelope of a pure tone is flat: the B-mode of a sinusoid is ~0 dB away from the ends
    tone = np.tile(np.cos(2 * np.pi * 0.1 * np.arange(400))[:, None], (1, 3))
    bt = bmode(tone, 60)[50:-50]
    assert np.abs(bt).max() < 0.1, np.abs(bt).max()
    assert np.all(bmode(np.zeros((10, 4))) == -50)
    with pytest.raises(InputError, match="NaN"):
        bmode(np.full((4, 4), np.nan))
    with pytest.raises(InputError, match="2D"):
        bmode(np.zeros(5))


def test_plot_bmode_and_field_axes_in_mm():
    rf = _rf((200, 16))
    sp, origin = (0.02, 0.2), (1.0, -1.6)
    ax = plot_bmode(rf, sp, origin)
    left, right, bottom, top = ax.images[0].get_extent()
    assert (left, right) == pytest.approx(extent_mm(rf.shape, sp, origin)[:2])
    assert bottom > top  # axial axis increases downwards
    assert right - left == pytest.approx(16 * 0.2) and bottom - top == pytest.approx(200 * 0.02)
    assert "mm" in ax.get_xlabel() and "mm" in ax.get_ylabel()
    assert len(ax.child_axes) == 1 and ax.child_axes[0].get_ylabel() == "echo level (dB)"  # its colour bar
    field = np.linspace(-1, 1, rf.size).reshape(rf.shape)
    field[:10] = np.nan
    fig, axes = plt.subplots(1, 2)
    a1 = plot_field(field, sp, origin, ax=axes[0], title="exx", vmin=-0.5, vmax=0.5)
    assert a1 is axes[0] and a1.get_title() == "exx"
    assert a1.images[0].get_clim() == (-0.5, 0.5)
    a2 = plot_field(field, sp, origin, ax=axes[1], overlay_bmode=rf, alpha=0.5)
    assert len(a2.images) == 2 and a2.images[1].get_alpha() == 0.5
    lo, hi = a2.images[1].get_clim()
    assert lo == -hi  # diverging map centred on 0
    with pytest.raises(InputError, match="shape"):
        plot_field(field, sp, overlay_bmode=rf[:-1])
    with pytest.raises(InputError, match="spacing"):
        plot_field(field, (0, 1))
    plt.close("all")


@pytest.mark.parametrize("with_reference", [False, True])
def test_plot_result_writes_png_of_expected_size(tmp_path, with_reference):
    p, t = _quad_mesh()
    res = _result(p, t, _affine_u(p, np.eye(2) * 0.01), shape=(40, 30))
    out = tmp_path / "r.png"
    fig = plot_result(res, out, reference=_rf((40, 30)) if with_reference else None, dpi=50,
                      figsize=(9.0, 6.0), overlay=with_reference)
    assert out.stat().st_size > 5000, out.stat().st_size
    img = plt.imread(out)
    assert img.shape[:2] == (300, 450), img.shape
    assert img[..., :3].std() > 0.05  # not a blank canvas
    titles = [a.get_title() for a in fig.axes]
    assert any("u_x" in s for s in titles) and any("xy" in s for s in titles), titles
    plt.close(fig)
    with pytest.raises(InputError, match="exx"):
        plot_result({k: v for k, v in res.items() if k != "exx"})


def test_render_mesh_offscreen(tmp_path):
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    p, t = _quad_mesh(8, 6)
    u = _affine_u(p, np.array([[0.01, 0.0], [0.0, -0.005]]))
    out = render_mesh(p, t, u[0::2], tmp_path / "m.png", window_size=(320, 240))
    img = plt.imread(out)
    assert img.shape[:2] == (240, 320), img.shape
    assert img[..., :3].std() > 0.02, img[..., :3].std()
    render_mesh(p, t, np.arange(t.shape[1]), tmp_path / "c.png", window_size=(200, 100))
    assert plt.imread(tmp_path / "c.png").shape[:2] == (100, 200)
    with pytest.raises(InputError, match="n_nodes"):
        render_mesh(p, t, np.zeros(3), tmp_path / "x.png")


def test_plot_quality_marks_poor_elements(tmp_path):
    from matplotlib.collections import PolyCollection

    from femreg.plot import plot_quality

    p, t = _quad_mesh(8, 6)
    q = np.linspace(0.0, 1.0, t.shape[1])
    fig = plot_quality(p, t, q, tmp_path / "q.png", threshold=0.5)
    assert (tmp_path / "q.png").stat().st_size > 0
    outlines = [c for c in fig.axes[0].collections if isinstance(c, PolyCollection)][1]
    assert len(outlines.get_paths()) == int(np.sum(q < 0.5))      # each element below the threshold outlined
    plt.close(fig)
    with pytest.raises(InputError, match="n_el values"):
        plot_quality(p, t, q[:-1])
