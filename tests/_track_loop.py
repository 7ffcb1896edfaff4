"""A small strain-regularised speckle loop for the command line's track tests: five frames of growing compression
and lateral stretch written as one .npy, and the track options that register it in seconds."""
import numpy as np

from femreg.synthetic import speckle_image, warp_image

SPACING = (0.05, 0.2)
ARGS = ["-r", "strain", "--alpha", "3", "--element-size", "1", "--margin", "1", "--spacing", "0.05", "0.2",
        "--no-progress"]


def write_loop(path):
    """Frames (5, 200, 50) float32 at ``path`` (.npy): frame s compressed 0.4 s % axially, stretched 0.2 s %."""
    rng = np.random.default_rng(11)
    ref = speckle_image((200, 50), SPACING, rng)
    frames = [ref] + [warp_image(ref, SPACING, (0, 0), lambda p, s=s: np.column_stack(
        [-s * 0.004 * p[:, 0], s * 0.002 * (p[:, 1] - 5.0)])) for s in (1, 2, 3, 4)]
    np.save(path, np.stack(frames).astype(np.float32))
    return path


def colorbar_labels(values, vmin, vmax):
    """The non-empty tick labels of the log colour bar :func:`femreg.plot.plot_mesh_values` draws for two elements
    holding ``values`` between ``vmin`` and ``vmax``."""
    import matplotlib.pyplot as plt

    from femreg.plot import plot_mesh_values

    pts = np.array([[0.0, 0.0, 1.0, 1.0, 2.0, 2.0], [0.0, 1.0, 0.0, 1.0, 0.0, 1.0]])
    cells = np.array([[0, 2], [2, 4], [3, 5], [1, 3]])
    fig, ax = plt.subplots()
    plot_mesh_values(pts, cells, np.asarray(values, float), ax=ax, log=True, vmin=vmin, vmax=vmax)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.collections[0].colorbar.ax.get_yticklabels() if t.get_text()]
    plt.close(fig)
    return labels


def assert_retry_recorded(folder, frame: int = 3):
    """A track folder's record of a retried increment: ``load_track`` lists ``frame``, its file holds the note and
    the frame before it holds none."""
    import femreg

    assert femreg.load_track(folder).retried == [frame]
    with np.load(folder / f"frame_{frame:03d}.npz") as z:
        assert str(z["retried"]).startswith("retried from a fresh start")
    with np.load(folder / f"frame_{frame - 1:03d}.npz") as z:
        assert "retried" not in z.files
