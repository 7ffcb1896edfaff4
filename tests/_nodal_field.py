"""A displacement field evaluated at a mesh's nodes, interleaved (u_x, u_y) per node as femreg stores it."""
import numpy as np


def nodal(mesh, f):
    """``f``: (n, 2) points (x, y) mm -> (n, 2) displacement (u_x, u_y) mm; returns (2 n_nodes,)."""
    v = f(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return u
