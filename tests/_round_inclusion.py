"""A round inclusion with a known axial strain for the recovery and measurement tests: u_x is the integral in x of
``exx = e0 (1 - (1 - ratio) s(r))`` (s a smooth step, 1 inside the disk of radius R), u_y = 0, so the axial strain
is round by construction; and the half-contrast contour radius along rays from the centre."""
import numpy as np


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
