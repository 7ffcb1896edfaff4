"""Volume pictures: what each slice shows (the voxels at the cut, strain in %, mm extents), NaN as background,
colour bars clear of the panels, a pyvista rendering written, bad input refused."""
import matplotlib.pyplot as plt
import numpy as np
import pytest

from femreg.errors import InputError
from femreg.volplot import plot_volume_slices, render_volume

SP = (0.05, 0.2, 0.25)
ORG = (2.0, -2.0, -1.5)
SHAPE = (60, 21, 13)


def _fields():
    i, j, k = np.indices(SHAPE).astype(float)
    exx = -0.01 + 1e-4 * i + 1e-5 * j - 2e-5 * k
    exx[:5] = np.nan                                          # outside the registered domain
    return dict(ux=1e-3 * i, exx=exx, quality=np.clip(k / 12.0, 0, 1))


def _images(fig):
    return [a for a in fig.axes if a.images]


def test_slices_show_the_cut_voxels_in_percent_with_mm_axes():
    f = _fields()
    at = (2.0 + 30 * SP[0], -2.0 + 4 * SP[1], -1.5 + 9 * SP[2])        # voxel (30, 4, 9)
    fig = plot_volume_slices(f, SP, ORG, keys=["exx", "quality"], at=at)
    axes = _images(fig)
    assert len(axes) == 6
    al, ae, le = (a.images[0] for a in axes[:3])
    want = 100.0 * f["exx"]
    assert np.allclose(al.get_array().filled(np.nan), want[:, :, 9], equal_nan=True)
    assert np.allclose(ae.get_array().filled(np.nan), want[:, 4, :], equal_nan=True)
    assert np.allclose(le.get_array().filled(np.nan), want[30, :, :].T, equal_nan=True)
    # voxel-edge extents in mm: lateral -2.1 .. 2.1, axial 1.975 .. 4.975 (depth down)
    assert al.get_extent() == pytest.approx([-2.1, -2.1 + 21 * 0.2, 1.975 + 60 * 0.05, 1.975])
    assert axes[0].get_xlabel() == "lateral y (mm)" and axes[1].get_xlabel() == "elevational z (mm)"
    # NaN rows are masked (drawn as background)
    assert al.get_array().mask[:5].all() and not al.get_array().mask[5:].any()


def test_colour_bars_clear_of_the_panels_and_labelled(tmp_path):
    rf = np.random.default_rng(0).standard_normal(SHAPE)
    fig = plot_volume_slices(_fields(), SP, ORG, reference=rf, out_png=tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 10_000
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    panels = _images(fig)
    bars = fig.volume_colorbars
    assert list(bars) == ["B-mode", "ux", "exx", "quality"]              # one per quantity
    labels = [b.ax.get_xlabel().replace("\n", " ") for b in bars.values()]
    assert labels == ["echo level (dB)", "axial displacement u_x (mm)", "axial strain e_xx (%)",
                      "quality (local NCC)"]
    for b in bars.values():
        bb = b.ax.get_tightbbox(r)
        assert bb.x0 >= -1 and bb.x1 <= fig.bbox.x1 + 1 and bb.y0 >= -1, "colour bar cut off"
        for a in panels:
            assert not bb.overlaps(a.get_window_extent(r)), "colour bar over a panel"
    bm = panels[0].images[0].get_array()
    assert bm.min() >= -50.0 and bm.max() <= 0.0 and bm.max() - bm.min() > 20.0   # dB below the volume's peak


def _layout(shape, spacing, keys=("ux", "exx", "eyy", "ezz", "quality")):
    i, j, k = np.indices(shape).astype(float)
    f = dict(ux=1e-3 * i, exx=-0.01 + 1e-4 * i + 1e-5 * j, eyy=0.005 + 1e-5 * k, ezz=0.004 + 1e-5 * j,
             quality=np.clip(k / shape[2], 0.0, 1.0))
    org = (1.0, -0.5 * shape[1] * spacing[1], -0.5 * shape[2] * spacing[2])
    at = tuple(o + (n // 3) * d for o, n, d in zip(org, shape, spacing))        # off-centre: markers must move
    fig = plot_volume_slices({k_: f[k_] for k_ in keys}, spacing, org, at=at, title="layout")
    fig.canvas.draw()
    return fig, fig.canvas.get_renderer(), at


@pytest.mark.parametrize("shape, spacing, kind", [
    ((96, 10, 8), (0.5, 1.0, 1.0), "deep"),           # 48 x 10 x 8 mm: the 7 MHz matrix probe's volumes
    ((20, 15, 15), (1.0, 2.0, 2.0), "shallow"),       # 20 x 30 x 30 mm: a wide matrix probe's
])
def test_layout_readable_for_deep_and_shallow_volumes(shape, spacing, kind):
    """The page stays landscape-like whatever the volume's aspect, every panel at its mm aspect and at least
    1 inch a side (within 2 %), none overlapping another, one colour bar per quantity under its own slices, and
    in each slice dashed lines where the other two cut, at the cut.  Measured: deep 14.6 x 10.2 in (h / w 0.70,
    axial-lateral panels 1.37 x 6.56 in), shallow 15.0 x 9.7 in (0.65, 2.80 x 1.86 in); the former layout (a
    row per quantity) drew the deep volume 8.8 x 42.7 in (4.84)."""
    fig, r, at = _layout(shape, spacing)
    w, h = fig.get_size_inches()
    assert 0.5 <= h / w <= 0.85 and w <= 15.5 and h <= 10.5, (w, h)
    mm = [n * d for n, d in zip(shape, spacing)]
    panels = fig.volume_axes
    assert len(panels) == 15 and len(_images(fig)) == 15
    boxes = {key: ax.get_window_extent(r) for key, ax in panels.items()}
    for (name, plane), ax in panels.items():
        bb = boxes[(name, plane)]
        hor, ver = {"axial-lateral": (1, 0), "axial-elevational": (2, 0), "lateral-elevational": (1, 2)}[plane]
        assert (bb.width / bb.height) == pytest.approx(mm[hor] / mm[ver], rel=0.02), (name, plane)
        assert min(bb.width, bb.height) >= 0.98 * fig.dpi, (name, plane)
        for other, ob in boxes.items():
            if other != (name, plane):
                assert not bb.overlaps(ob), ((name, plane), other)
        # slice markers: one vertical, one horizontal line, at the other two slices' positions
        marks = [ln for ln in ax.lines if ln.get_gid() == "slice"]
        assert len(marks) == 2
        v, hz = marks[0].get_xdata()[0], marks[1].get_ydata()[0]
        assert (v, hz) == pytest.approx((at[hor], at[ver]), abs=0.5 * max(spacing)), (name, plane)
        symbol = {"ux": "u_x", "exx": "e_xx", "eyy": "e_yy", "ezz": "e_zz"}.get(name, name)
        assert ax.get_title().startswith(f"{symbol}, {'xyz'[({0, 1, 2} - {hor, ver}).pop()]} = ")
        tb = ax.title.get_window_extent(r)
        assert tb.x0 >= -1 and tb.x1 <= fig.bbox.x1 + 1 and not tb.overlaps(fig._suptitle.get_window_extent(r))
    bars = fig.volume_colorbars
    assert list(bars) == ["ux", "exx", "eyy", "ezz", "quality"]
    for name, cb in bars.items():
        bb = cb.ax.get_window_extent(r)
        own = [boxes[(name, p)] for p in ("axial-lateral", "axial-elevational", "lateral-elevational")]
        assert bb.y1 <= min(b.y0 for b in own)                          # under its slices
        assert min(b.x0 for b in own) - 2 <= 0.5 * (bb.x0 + bb.x1) <= max(b.x1 for b in own) + 2
        assert all(cb.mappable.norm is ax.images[0].norm or (cb.mappable.norm.vmin, cb.mappable.norm.vmax)
                   == (ax.images[0].norm.vmin, ax.images[0].norm.vmax) for ax in (panels[(name, p)] for p in
                   ("axial-lateral", "axial-elevational", "lateral-elevational")))
    plt.close(fig)


def test_a_thin_axis_is_stretched_and_labelled_so():
    """A 5 x 50 x 50 mm volume (1:10): its axial axis is drawn 1.7x (longest / 6), said in the label; the page
    stays under 20 x 10 in (measured 19.75 x 8.35 in)."""
    fig, r, _ = _layout((5, 25, 25), (1.0, 2.0, 2.0), keys=("exx", "quality"))
    w, h = fig.get_size_inches()
    assert w <= 20.0 and h <= 10.5
    ax = fig.volume_axes[("exx", "axial-lateral")]
    assert ax.get_ylabel() == "axial x (mm)\nstretched 1.7x" and ax.get_xlabel() == "lateral y (mm)"
    bb = ax.get_window_extent(r)
    assert (bb.width / bb.height) == pytest.approx(50.0 / 5.0 / (10.0 / 6.0), rel=0.02)
    assert fig.volume_axes[("exx", "lateral-elevational")].get_aspect() == 1.0
    plt.close(fig)


def test_bad_input():
    f = _fields()
    with pytest.raises(InputError, match="3D"):
        plot_volume_slices({"exx": np.zeros((4, 4))}, SP)
    with pytest.raises(InputError, match="outside the volume"):
        plot_volume_slices(f, SP, ORG, at=(100.0, 0.0, 0.0))
    with pytest.raises(InputError, match="no ezz"):
        plot_volume_slices(f, SP, ORG, keys=["ezz"])
    with pytest.raises(InputError, match="spacing"):
        plot_volume_slices(f, (0.1, 0.2), ORG)


def test_pyvista_rendering_written(tmp_path):
    pytest.importorskip("pyvista")
    f = _fields()
    for mode in ("slices", "iso"):
        out = render_volume(f, SP, ORG, tmp_path / f"{mode}.png", key="exx", mode=mode)
        import matplotlib.image as mpimg

        img = mpimg.imread(out)
        assert img.shape[:2] == (700, 900)
        colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
        assert len(colours) > 50, f"{mode}: a nearly blank picture ({len(colours)} colours)"


def test_pyvista_rendering_of_a_deep_volume_is_portrait(tmp_path):
    """A 40 x 5 x 4 mm volume renders in a 700 x 1000 window, the box spanning at least 650 px of its height
    (measured 691 px; in the former 900 x 700 window 603 px)."""
    pytest.importorskip("pyvista")
    import matplotlib.image as mpimg

    i, j, k = np.indices((40, 5, 4)).astype(float)
    out = render_volume(dict(exx=-0.01 + 1e-4 * i + 1e-4 * j), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                        tmp_path / "deep.png", key="exx")
    img = mpimg.imread(out)
    assert img.shape[:2] == (1000, 700)
    body = img[:, : int(0.75 * img.shape[1]), :3]               # left of the colour bar
    rows = np.nonzero((body < 0.9).any(axis=(1, 2)))[0]
    assert rows.max() - rows.min() >= 650 and rows.min() > 0 and rows.max() < img.shape[0] - 1
