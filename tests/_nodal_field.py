"""A displacement field evaluated at a mesh's nodes, interleaved (u_x, u_y) per node as femreg stores it."""
import numpy as np


def nodal(mesh, f):
    """``f``: (n, 2) points (x, y) mm -> (n, 2) displacement (u_x, u_y) mm; returns (2 n_nodes,)."""
    v = f(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return u


def band(x0, x1, slide=0.2):
    """1 % compression and a lateral slide across the layer x0 < x < x1 mm (its two faces: shear-traction jumps)."""
    def f(p):
        x = p[:, 0]
        return np.column_stack([-0.01 * x, slide * np.clip((x - x0) / (x1 - x0), 0.0, 1.0)])
    return f


def step(x0, e1=-0.01, e2=-0.004):
    """Axial strain e1 above depth x0 mm, e2 below: a jump of the normal traction only."""
    def f(p):
        x, y = p[:, 0], p[:, 1]
        return np.column_stack([np.where(x < x0, e1 * x, e1 * x0 + e2 * (x - x0)), 0.005 * y])
    return f
