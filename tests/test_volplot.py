"""Volume pictures: what each slice shows (the voxels at the cut, strain in %, mm extents), NaN as background,
colour bars clear of the panels, a pyvista rendering written, bad input refused."""
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
    bars = [c for a in panels for c in a.child_axes]
    assert len(bars) == 4                                     # B-mode, ux, exx, quality: one per row
    labels = [b.get_ylabel().replace("\n", " ") for b in bars]
    assert labels == ["echo level (dB)", "axial displacement u_x (mm)", "axial strain e_xx (%)",
                      "quality (local NCC)"]
    for b in bars:
        bb = b.get_tightbbox(r)
        assert bb.x1 <= fig.bbox.x1 + 1, "colour bar cut off"
        for a in panels:
            assert not bb.overlaps(a.get_window_extent(r)), "colour bar over a panel"
    bm = panels[0].images[0].get_array()
    assert bm.min() >= -50.0 and bm.max() <= 0.0 and bm.max() - bm.min() > 20.0   # dB below the volume's peak


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
