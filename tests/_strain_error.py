"""A helper of the refinement tests: a registration's total strain error against a simulated pair's truth."""
import numpy as np


def total_strain_error(res, data) -> float:
    """Total strain error % (e_xx, e_yy, 2 e_xy) over the pixels 2 mm inside the image, every 5th row."""
    n0, n1 = res.shape
    truth = data.true_strain(res.pixel_points()).reshape(n0, n1, 3)
    g = res.on_grid()
    est = np.stack([g["exx"], g["eyy"], g["exy"]], -1)
    i0, j0 = int(2 / res.spacing[0]), int(2 / res.spacing[1])
    sl = (slice(i0, n0 - i0, 5), slice(j0, n1 - j0))
    w = np.array([1.0, 1.0, 2.0])
    return 100 * float(np.sqrt(np.sum(w * (est[sl] - truth[sl]) ** 2) / np.sum(w * truth[sl] ** 2)))
