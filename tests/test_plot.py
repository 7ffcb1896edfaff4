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
    # the picture says what the outlines are
    assert f"outlined: {int(np.sum(q < 0.5))} of {q.size} elements below 0.5" in fig.axes[0].get_title()
    plt.close(fig)
    with pytest.raises(InputError, match="n_el values"):
        plot_quality(p, t, q[:-1])


# ---------------------------------------------------------------------------------------------- conventions
def test_colour_scale_follows_the_sign_of_the_data():
    from femreg.plot import DIVERGING_CMAP, SEQUENTIAL_CMAP, colour_scale

    rng = np.random.default_rng(0)
    comp = -0.01 - 0.004 * rng.random((50, 40))                  # compression everywhere
    cmap, lo, hi = colour_scale(comp)
    assert cmap == SEQUENTIAL_CMAP + "_r" and comp.min() <= lo < hi <= comp.max() < 0
    cmap, lo, hi = colour_scale(-comp)
    assert cmap == SEQUENTIAL_CMAP and 0 < lo < hi
    signed = np.linspace(-1.0, 2.0, 300)
    cmap, lo, hi = colour_scale(signed)
    assert cmap == DIVERGING_CMAP and lo == -hi and hi == pytest.approx(np.percentile(signed, 99))
    # a few outliers of the other sign (< 1 %) do not make the map diverging
    spiky = comp.copy()
    spiky.flat[:5] = 0.05
    assert colour_scale(spiky)[0] == SEQUENTIAL_CMAP + "_r"
    assert colour_scale(np.full((3, 3), np.nan))[0] == DIVERGING_CMAP


def test_a_sliver_of_the_other_sign_keeps_the_sequential_map():
    """The axial displacement of the in vivo pair seq299 0 -> 1: negative almost everywhere, its 1st and 99th
    percentiles -0.0804 and +0.0013 mm (measured).  Symmetric limits would leave half the colour bar unused; the
    sequential map spans the data.  Both signs with a fair share (the strains there: -0.81 / +0.25 %) stay
    diverging."""
    from femreg.plot import DIVERGING_CMAP, SEQUENTIAL_CMAP, SIGNED_SHARE, colour_scale

    ux = np.r_[np.linspace(-0.0885, -0.0001, 980), np.linspace(0.0001, 0.0027, 20)]
    lo1, hi99 = np.percentile(ux, [1, 99])
    assert lo1 < 0 < hi99 < 0.05 * -lo1
    cmap, lo, hi = colour_scale(ux)
    assert cmap == SEQUENTIAL_CMAP + "_r" and (lo, hi) == pytest.approx((lo1, hi99))
    assert colour_scale(-ux)[0] == SEQUENTIAL_CMAP                  # mostly positive: bright = large
    exx = np.r_[np.linspace(-0.81, 0.0, 800), np.linspace(0.0, 0.25, 200)]
    cmap, lo, hi = colour_scale(exx)
    assert cmap == DIVERGING_CMAP and lo == -hi
    # the rule's edge: the smaller end at SIGNED_SHARE of the larger is diverging, just below it is not
    for share, want in ((SIGNED_SHARE * 1.05, DIVERGING_CMAP), (SIGNED_SHARE * 0.95, SEQUENTIAL_CMAP + "_r")):
        v = np.r_[np.full(50, -1.0), np.linspace(-1.0, share, 900), np.full(50, share)]
        assert colour_scale(v)[0] == want, share


def _compression_result(shape=(40, 30), **kw):
    p, t = _quad_mesh()
    res = _result(p, t, _affine_u(p, np.diag([-0.02, 0.01])), shape=shape)
    x = np.arange(shape[0])[:, None] * np.ones(shape[1])
    res.update(ux=-0.02 * x * 0.05, uy=np.linspace(-1, 1, shape[1]) * np.ones((shape[0], 1)) * 0.01,
               exx=np.full(shape, -0.02) + 1e-4 * x, eyy=np.full(shape, 0.01), exy=np.zeros(shape) + 1e-5 * (x - 20))
    res.update(kw)
    return res


def test_summary_figure_units_maps_and_no_banner_on_success(tmp_path):
    from femreg.plot import DIVERGING_CMAP, FAILED_COLOUR, SEQUENTIAL_CMAP

    fig = plot_result(_compression_result(), tmp_path / "ok.png", dpi=40)
    bars = {a.get_title(): a.child_axes[0] for a in fig.axes if a.child_axes}
    labels = {k: v.get_ylabel() for k, v in bars.items()}
    for k, lab in labels.items():
        if "strain" in k:
            assert lab.endswith("(%)"), (k, lab)
        elif "displacement" in k:
            assert lab.endswith("(mm)"), (k, lab)
    exx_ax = next(a for a in fig.axes if a.get_title().startswith("axial strain"))
    im = exx_ax.images[0]
    assert im.get_cmap().name == SEQUENTIAL_CMAP + "_r"                 # all compression
    lo, hi = im.get_clim()
    assert -2.0 <= lo < hi <= -2.0 + 0.01 * 40 + 1e-9                   # in %, not a fraction
    exy_ax = next(a for a in fig.axes if a.get_title().startswith("shear strain"))
    assert exy_ax.images[0].get_cmap().name == DIVERGING_CMAP           # changes sign
    assert "FAILED" not in fig.get_suptitle()
    plt.close(fig)
    fig = plot_result(_compression_result(ncc_before=0.188, ncc_after=0.861), dpi=40)
    assert "NCC 0.188 -> 0.861 (before -> after)" in fig.get_suptitle()
    assert not any(getattr(p, "get_edgecolor", lambda: None)() is not None and
                   matplotlib.colors.same_color(p.get_edgecolor(), FAILED_COLOUR) for p in fig.patches)
    plt.close(fig)


def test_failed_result_carries_a_banner_with_its_message(tmp_path):
    from femreg.plot import FAILED_COLOUR

    res = _compression_result(success=False, message="62 % of the elements do not match")
    fig = plot_result(res, tmp_path / "f.png", dpi=40)
    title = fig.get_suptitle()
    assert title.startswith("REGISTRATION FAILED") and "62 % of the elements" in title.replace("\n", " ")
    assert any(matplotlib.colors.same_color(p.get_edgecolor(), FAILED_COLOUR) for p in fig.patches)
    img = plt.imread(tmp_path / "f.png")[..., :3]
    red = (img[..., 0] > 0.6) & (img[..., 1] < 0.2) & (img[..., 2] < 0.2)
    assert red[:10].mean() > 0.3                                        # the top rows of the PNG are red
    plt.close(fig)


def test_region_outside_the_mesh_is_hatched_and_labelled(tmp_path):
    shape = (40, 30)
    res = _compression_result(shape)
    for k in ("ux", "uy", "exx", "eyy", "exy"):
        res[k][25:] = np.nan                                             # no result below 1.25 mm
    res["excluded"] = "no echo below 1.2 mm"
    fig = plot_result(res, tmp_path / "x.png", dpi=40)
    panels = [a for a in fig.axes if a.get_title()]
    for a in panels:
        hatched = [c for c in a.collections if any(getattr(c, "hatches", None) or [])]
        assert hatched, a.get_title()
    texts = [t.get_text() for t in panels[0].texts]
    assert any("no echo below 1.2 mm" in t.replace("\n", " ") for t in texts), texts
    assert fig._supxlabel.get_text() == "hatched: outside the registered mesh (no displacement or strain there); "\
        "no echo below 1.2 mm"                                          # the margin strips are hatched too
    plt.close(fig)
    fig = plot_result(_compression_result(shape), dpi=40)               # everything registered: nothing hatched
    assert not any(any(getattr(c, "hatches", None) or []) for a in fig.axes for c in a.collections)
    plt.close(fig)


def test_inversion_figure_recovered_strain_and_labels_apart(tmp_path):
    from skfem import MeshQuad1

    from femreg.fields import recovered_strains
    from femreg.inversion import InversionResult
    from femreg.plot import plot_inversion

    m = MeshQuad1.init_tensor(np.linspace(0, 20, 11), np.linspace(-8, 8, 9))
    u = np.zeros(2 * m.p.shape[1])
    u[0::2] = -0.01 * m.p[0] - 2e-4 * m.p[0] ** 2 / 2                  # exx = -1 % - 0.02 % per mm of depth
    res = InversionResult(mesh=m, mu=np.exp(0.3 * np.sin(m.p[:, m.t].mean(axis=1)[0])), model="plane-stress",
                          lambda_bar=2.0, beta=0.01, u_measured=u, success=True, message="ok")
    res.uncertainty = np.full(m.t.shape[1], 0.1)
    fig = plot_inversion(res, tmp_path / "mu.png", dpi=60)
    axes = [a for a in fig.axes if a.get_title()]
    assert len(axes) == 3 and "uncertainty" in axes[1].get_title()
    strain_ax = axes[2]
    assert strain_ax.child_axes[0].get_ylabel().endswith("(%)")
    img = strain_ax.images[0].get_array()
    # the recovered (continuous) strain, not element-wise: values along depth match its nodal interpolation
    ns = recovered_strains(m.p, m.t, u)
    col = np.asarray(img[:, img.shape[1] // 2], float)
    assert col.min() == pytest.approx(100 * ns[:, 0].min(), rel=1e-6)
    assert len(np.unique(np.round(col, 9))) > 5 * 10                   # more levels than the 10 element rows
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for left, right in zip(axes[:-1], axes[1:]):
        bar_label = left.child_axes[0].yaxis.label.get_window_extent(r)
        right_box = right.get_tightbbox(r)
        assert bar_label.x1 < right_box.x0, (left.get_title(), bar_label, right_box)
    plt.close(fig)
    res.uncertainty[:3] = np.nan                                        # elements the data do not constrain
    # and a failed inversion, on the same figure (each figure takes seconds to lay out)
    res.success, res.message = False, "beta at the edge of its grid"
    fig = plot_inversion(res, dpi=40)
    assert "FAILED" in fig.get_suptitle() and "beta at the edge" in fig.get_suptitle()
    title = [a for a in fig.axes if a.get_title()][1].get_title()
    assert f"blank: 3 of {m.t.shape[1]} elements the data do not constrain" in title, title
    # the blank elements show the panel's grey, not white, which magma's top (largest uncertainty) nearly is
    import matplotlib
    face = np.asarray(matplotlib.colors.to_rgb([a for a in fig.axes if a.get_title()][1].get_facecolor()))
    assert np.abs(face - np.asarray(matplotlib.colormaps["magma"](1.0)[:3])).max() > 0.3, face     # white: 0.25
    plt.close(fig)


@pytest.mark.parametrize("shape, spacing", [((40, 30), (0.05, 0.075)), ((200, 128), (0.2, 0.2))])
def test_summary_colour_bars_clear_of_the_next_panel(shape, spacing):
    """The colour bars are insets of their panels (as tall as the image), which the layout does not reserve room
    for; on a 40 x 26 mm image (a scanner frame) they reached the next panel's labels until the gaps were fitted."""
    fig = plot_result(_compression_result(shape, spacing=np.array(spacing)), dpi=50)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    panels = [a for a in fig.axes if a.get_title()]
    rows = [panels[:3], panels[3:]]
    for row in rows:
        for left, right in zip(row[:-1], row[1:]):
            if not left.child_axes:                                    # the mesh panel has no colour bar
                continue
            bar = left.child_axes[0].get_tightbbox(r)
            assert bar.x1 < right.get_tightbbox(r).x0, (left.get_title(), shape)
            assert abs(left.child_axes[0].get_window_extent(r).height - left.get_window_extent(r).height) < 2
    plt.close(fig)


def test_labels_stay_inside_the_figure_and_clear_of_the_failure_frame():
    """The in vivo mu.png (flagged, 1320 x 583 px): the depth label began 1 px from the left edge and the last
    colour bar's label ended 1 px from the right one, both under the red frame (3 pt of it inside the figure)."""
    from skfem import MeshQuad1

    from femreg.inversion import InversionResult
    from femreg.plot import EDGE_MARGIN_IN, plot_inversion

    m = MeshQuad1.init_tensor(np.linspace(1, 37, 31), np.linspace(1, 24.5, 24))     # the in vivo mesh's extent
    u = np.zeros(2 * m.p.shape[1])
    u[0::2] = -0.01 * m.p[0]
    for success in (True, False):
        res = InversionResult(mesh=m, mu=np.exp(np.sin(m.p[:, m.t].mean(axis=1)[0])), model="plane-stress",
                              lambda_bar=2.0, beta=0.1, u_measured=u, success=success,
                              message="ok" if success else "FLAGGED: the misfit " + "stays above the limit " * 12)
        res.uncertainty = np.full(m.t.shape[1], 2.5)
        fig = plot_inversion(res, dpi=100)
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        clear = (EDGE_MARGIN_IN + (0 if success else 6 / 72 / 2)) * fig.dpi - 1      # px, 1 px of rounding
        boxes = [b for a in fig.axes for b in [a.get_tightbbox(r)] + [c.get_tightbbox(r) for c in a.child_axes]]
        assert min(b.x0 for b in boxes) >= clear, (success, min(b.x0 for b in boxes), clear)
        assert max(b.x1 for b in boxes) <= fig.bbox.width - clear, (success, max(b.x1 for b in boxes))
        assert min(b.y0 for b in boxes) >= clear, (success, min(b.y0 for b in boxes))
        panels = [a for a in fig.axes if a.get_title()]
        for left, right in zip(panels[:-1], panels[1:]):                 # and still apart from each other
            assert left.child_axes[0].get_tightbbox(r).x1 < right.get_tightbbox(r).x0
        plt.close(fig)


def test_log_colour_bar_ticks_are_plain_numbers():
    # a modulus image over three decades (in vivo seq304 frames 0 -> 3: 0.07-500 x the median) labelled its 100
    # "1e+02" beside 0.1, 1 and 10
    from femreg.plot import plot_mesh_values

    pts = np.array([[0.0, 0.0, 1.0, 1.0, 2.0, 2.0], [0.0, 1.0, 0.0, 1.0, 0.0, 1.0]])
    cells = np.array([[0, 2], [2, 4], [3, 5], [1, 3]])
    fig, ax = plt.subplots()
    plot_mesh_values(pts, cells, np.array([0.05, 500.0]), ax=ax, log=True)
    fig.canvas.draw()
    cax = ax.collections[0].colorbar.ax
    labels = [t.get_text() for t in cax.get_yticklabels() if t.get_text()]
    plt.close(fig)
    assert "100" in labels and "10" in labels, labels
    assert not any("e+" in s or "e-" in s for s in labels), labels
