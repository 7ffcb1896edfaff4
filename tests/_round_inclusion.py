"""A round inclusion with a known axial strain for the recovery and measurement tests: u_x is the integral in x of
``exx = e0 (1 - (1 - ratio) s(r))`` (s a smooth step, 1 inside the disk of radius R), u_y = 0, so the axial strain
is round by construction; and the half-contrast contour radius along rays from the centre."""
import numpy as np
from scipy import ndimage


def exx_true(P, centre=(10.0, 0.0), R=4.0, e0=-0.01, ratio=0.4, width=0.15):
    r = np.hypot(P[:, 0] - centre[0], P[:, 1] - centre[1])
    s = 0.5 * (1.0 - np.tanh((r - R) / width))
    return e0 * (1.0 - (1.0 - ratio) * s)


def nodal_u(p, x_start=0.0, n=4000, **kw):
    """Interleaved nodal u (2 n_nodes,) of the field at the points ``p`` (2, n_nodes) mm."""
    u = np.zeros(2 * p.shape[1])
    s = np.linspace(0.0, 1.0, n)
    for i in range(p.shape[1]):
        xs = x_start + s * (p[0, i] - x_start)
        v = exx_true(np.column_stack([xs, np.full(n, p[1, i])]), **kw)
        u[2 * i] = np.trapezoid(v, xs)
    return u


def contour_radii(img, spacing, origin, centre, R, level, n=72):
    """Radius (mm) along ``n`` rays from ``centre`` where ``img`` (pixel grid) first crosses ``level``."""
    rs = np.arange(0.2 * R, 2.0 * R, 0.005)
    out = np.full(n, np.nan)
    for k, th in enumerate(2 * np.pi * np.arange(n) / n):
        X, Y = centre[0] + rs * np.cos(th), centre[1] + rs * np.sin(th)
        v = ndimage.map_coordinates(np.nan_to_num(img, nan=level), [(X - origin[0]) / spacing[0],
                                                                   (Y - origin[1]) / spacing[1]], order=1)
        c = np.flatnonzero(np.sign(v[1:] - level) != np.sign(v[:-1] - level))
        if c.size:
            i = c[0]
            out[k] = rs[i] + (level - v[i]) / (v[i + 1] - v[i]) * (rs[i + 1] - rs[i])
    return out
