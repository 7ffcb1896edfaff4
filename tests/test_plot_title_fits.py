"""A figure title longer than the figure is wrapped inside it (femreg.plot.fit_colorbars)."""
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
