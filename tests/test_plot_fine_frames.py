"""Pictures of a fine (15 MHz, 0.1 mm pitch) loop: a title longer than the figure is wrapped inside it
(femreg.plot.fit_colorbars); the shear map's element-width panel keeps a colour range around one cell."""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from femreg.plot import EDGE_MARGIN_IN, fit_colorbars  # noqa: E402

# a track frame's title as `femreg plot` writes it (128 characters: one line ran past both edges of 10.8 in)
TITLE = ("frame 0 -> 11 (accumulated), regulariser momentum-stress, alpha 0.133, NCC -0.114 -> 0.951 "
         "(frame 10 -> 11, before -> after)")


def _figure(width_in, title):
    fig, axes = plt.subplots(2, 3, figsize=(width_in, 9.0), layout="constrained")
    for ax in axes.ravel():
        ax.imshow(np.random.default_rng(0).random((20, 20)))
    fig.suptitle(title)
    fit_colorbars(fig, [list(axes[0]), list(axes[1])])
    fig.draw_without_rendering()
    return fig


def test_long_title_wrapped_inside_the_figure():
    for width in (10.8, 7.0):
        fig = _figure(width, TITLE)
        box = fig._suptitle.get_window_extent(fig.canvas.get_renderer())
        margin = EDGE_MARGIN_IN * fig.dpi
        assert box.x0 >= margin - 1 and box.x1 <= fig.bbox.width - margin + 1, (width, box)
        text = fig._suptitle.get_text()
        assert " ".join(text.split()) == TITLE and text.count("\n") <= 2, text
        plt.close(fig)


def test_short_title_left_as_it_is():
    fig = _figure(10.8, "frames 2 -> 3, alpha 0.133")
    assert fig._suptitle.get_text() == "frames 2 -> 3, alpha 0.133"
    plt.close(fig)


def test_shear_map_cells_panel_keeps_a_range_around_one():
    """Element widths of 2.0 and 2.5 lateral speckle cells (5 and 6 lines of a 0.1 mm pitch) alternated in
    full-scale stripes over the data's own range; the colours now span at least 0.5-4 cells."""
    from femreg.plot import CELLS_RANGE, plot_shear

    x, y = np.meshgrid(np.arange(0.0, 4.01, 0.5), np.arange(0.0, 5.01, 0.5), indexing="ij")
    p = np.vstack([x.ravel(), y.ravel()])
    idx = np.arange(p.shape[1]).reshape(x.shape)
    t = np.vstack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()])
    n = t.shape[1]
    cells = np.where(np.arange(n) % 2 == 0, 2.0, 2.5)
    fig = plot_shear(p, t, {"exy": np.zeros(n), "sigma": np.ones(n), "lateral_cells": cells})
    lo, hi = fig.axes[2].collections[0].norm.vmin, fig.axes[2].collections[0].norm.vmax
    assert (lo, hi) == CELLS_RANGE, (lo, hi)
    # the two widths one step of a log scale of 8 apart: log(2.5 / 2) / log(8) = 0.11 of the colours (was 1)
    assert np.log(2.5 / 2.0) / np.log(hi / lo) < 0.12
    plt.close(fig)
    wide = np.where(np.arange(n) % 2 == 0, 0.2, 9.0)       # data beyond the least range keep their own
    fig = plot_shear(p, t, {"exy": np.zeros(n), "sigma": np.ones(n), "lateral_cells": wide})
    norm = fig.axes[2].collections[0].norm
    assert norm.vmin <= 0.2 + 1e-9 and norm.vmax >= 9.0 - 1e-9
    plt.close(fig)


def test_narrow_axial_strain_range_is_said_in_its_title():
    """Full-scale colours over a few percent of the mean read as contrast that is not there: the axial strain
    panel's title says how narrow its range is (femreg.plot.narrow_span_note); a strain image with contrast gets
    nothing."""
    from femreg.plot import NARROW_SPAN, narrow_span_note, plot_result

    rng = np.random.default_rng(1)
    flat = -0.0076 + 0.0001 * rng.standard_normal((60, 40))          # -0.74 .. -0.78 %: 5 % of the mean
    lesion = flat.copy()
    lesion[20:40, 15:25] *= 0.45                                      # a stiff lesion at strain ratio 2.2
    note = narrow_span_note(flat)
    span = float(note.split("span ")[1].split(" %")[0])
    assert 2.0 < span < 100 * NARROW_SPAN, note
    assert narrow_span_note(lesion) == ""
    d = dict(ux=np.zeros((60, 40)), uy=np.zeros((60, 40)), exx=flat, eyy=-0.5 * flat, exy=0 * flat,
             spacing=np.array([0.1, 0.1]), origin=np.zeros(2))
    fig = plot_result(d, reference=rng.standard_normal((60, 40)))
    titles = [ax.get_title() for ax in fig.axes]
    assert any("axial strain" in t and "colours span" in t for t in titles), titles
    plt.close(fig)
