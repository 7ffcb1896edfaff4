"""Displacement and strain of a trilinear hexahedral FE field (volumes): the 3D form of :mod:`femreg.fields`.

Small strains in the order :data:`STRAIN_COMPONENTS_3D` = (exx, eyy, ezz, exy, exz, eyz), tensor shear
(``exy = (dux/dy + duy/dx) / 2``).  As in 2D the reported strain is by default the *recovered* one: the
element-centre strains (the superconvergent points of trilinear hexahedra) averaged at each node (Zienkiewicz &
Zhu 1987, simple averaging) and interpolated trilinearly; ``strain="element"`` is the gradient of the trilinear
field at the point.  ``u`` is the interleaved nodal vector ``[ux0, uy0, uz0, ux1, ...]`` (scikit-fem's
``ElementVector(ElementHex1())`` DOF order), lengths in mm.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .errors import InputError
from .quadrature import ELEMENT_CENTRE_RULE_3D

__all__ = ["STRAIN_COMPONENTS_3D", "FIELDS_3D", "centre_gradients", "element_strains_3d",
           "element_strain_operator_3d", "nodal_average_3d", "recovered_strains_3d", "HexLocator"]

#: The six strain components of a volume, in this order everywhere.
STRAIN_COMPONENTS_3D = ("exx", "eyy", "ezz", "exy", "exz", "eyz")
#: Displacement components of a volume.
DISPLACEMENT_COMPONENTS_3D = ("ux", "uy", "uz")
#: Everything sampled on a volume's grid.
FIELDS_3D = DISPLACEMENT_COMPONENTS_3D + STRAIN_COMPONENTS_3D
#: Points per pass of :meth:`HexLocator.sample` (its temporaries: ~0.7 kB per point).
SAMPLE_CHUNK = 1 << 18
#: (a, b) of each strain component: e_ab = (du_a/dx_b + du_b/dx_a) / 2.
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def strain_from_gradient(grad) -> np.ndarray:
    """(3, 3, n) displacement gradients du_a/dx_b -> (n, 6) strains in :data:`STRAIN_COMPONENTS_3D` order."""
    return np.column_stack([0.5 * (grad[a, b] + grad[b, a]) for a, b in _PAIRS])


def centre_gradients(mesh):
    r"""``(G, volumes)``: ``G[a][b]`` (n_el, 3 n_nodes) csr with ``G[a][b] @ u`` = :math:`\partial u_a/\partial
    x_b` at each element centre (1-point rule, scikit-fem ``ElementVector(ElementHex1())``), and the element
    volumes (mm^3)."""
    from skfem import Basis, ElementHex1, ElementVector

    basis = Basis(mesh, ElementVector(ElementHex1()), quadrature=ELEMENT_CENTRE_RULE_3D)
    n_el = mesh.t.shape[1]
    dofs = basis.element_dofs
    rows = np.broadcast_to(np.arange(n_el), dofs.shape).ravel()
    grads = np.stack([basis.basis[i][0].grad[:, :, :, 0] for i in range(basis.Nbfun)])    # (Nb, 3, 3, n_el)
    G = [[sp.csr_matrix((grads[:, a, b].ravel(), (rows, dofs.ravel())), shape=(n_el, basis.N)) for b in range(3)]
         for a in range(3)]
    return G, basis.dx[:, 0].copy()


def element_strain_operator_3d(mesh) -> sp.csr_matrix:
    """(6 n_el, 3 n_nodes): the element-centre strains, components stacked in :data:`STRAIN_COMPONENTS_3D` order."""
    G, _ = centre_gradients(mesh)
    return sp.vstack([0.5 * (G[a][b] + G[b][a]) for a, b in _PAIRS]).tocsr()


def element_strains_3d(mesh, u) -> np.ndarray:
    """(n_el, 6) element-centre strains of the nodal vector ``u`` (3 n_nodes,) mm."""
    u = np.asarray(u, float)
    if u.shape != (3 * mesh.p.shape[1],):
        raise InputError(f"u must have 3 * n_nodes = {3 * mesh.p.shape[1]} entries, got {u.shape}")
    return (element_strain_operator_3d(mesh) @ u).reshape(6, -1).T


def nodal_average_3d(mesh, cell_values) -> np.ndarray:
    """Mean of the values (n_el, k) of the elements around each node -> (n_nodes, k)."""
    t = np.asarray(mesh.t)
    v = np.asarray(cell_values, float).reshape(t.shape[1], -1)
    n = mesh.p.shape[1]
    count = np.bincount(t.ravel(), minlength=n).astype(float)
    out = np.column_stack([np.bincount(t.ravel(), weights=np.tile(v[:, k], t.shape[0]), minlength=n)
                           for k in range(v.shape[1])])
    with np.errstate(invalid="ignore", divide="ignore"):
        return out / count[:, None]


def recovered_strains_3d(mesh, u) -> np.ndarray:
    """Recovered nodal strains (n_nodes, 6): the nodal average of the element-centre strains."""
    return nodal_average_3d(mesh, element_strains_3d(mesh, u))


class HexLocator:
    """Point location on an axis-aligned tensor hexahedral mesh (arithmetic: one searchsorted per axis)."""

    def __init__(self, mesh):
        from .voxels import tensor_axes_3d, _cell_index

        ta = tensor_axes_3d(mesh)
        if ta is None:
            raise InputError("volume results need an axis-aligned tensor hexahedral mesh")
        self.mesh = mesh
        self.axes, self.node = ta
        self.cell = _cell_index(mesh, self.node)

    def locate(self, points):
        """``(inside, e, X, nodes)`` of points (n, 3) mm: inside mask, per-axis cell index (3, n), reference
        coordinates (3, n) in [0, 1], the 8 corner nodes (8, n) in (i, j, k) binary order."""
        pts = np.asarray(points, float).reshape(-1, 3)
        e, X, inside = [], [], np.ones(len(pts), bool)
        for a in range(3):
            ax = self.axes[a]
            tol = 1e-9 * (ax[-1] - ax[0])
            ea = np.clip(np.searchsorted(ax, pts[:, a], side="right") - 1, 0, ax.size - 2)
            Xa = (pts[:, a] - ax[ea]) / (ax[ea + 1] - ax[ea])
            inside &= (pts[:, a] >= ax[0] - tol) & (pts[:, a] <= ax[-1] + tol)
            e.append(ea)
            X.append(np.clip(Xa, 0.0, 1.0))
        e, X = np.array(e), np.array(X)
        nodes = np.stack([self.node[e[0] + i, e[1] + j, e[2] + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        return inside, e, X, nodes

    def sample(self, u, points, nodal_strain=None, chunk: int = SAMPLE_CHUNK) -> dict:
        """``ux, uy, uz`` and the six strains at ``points`` (n, 3); NaN outside the mesh.  Strains: the recovered
        ``nodal_strain`` (n_nodes, 6) interpolated, or with None the gradient of the trilinear field.  Points are
        taken ``chunk`` at a time (the weights of one point take ~0.7 kB; the values do not depend on it)."""
        pts = np.asarray(points, float).reshape(-1, 3)
        u = np.asarray(u, float)
        if len(pts) <= chunk:
            return self._sample(u, pts, nodal_strain)
        out = {name: np.empty(len(pts)) for name in FIELDS_3D}
        for a in range(0, len(pts), chunk):
            for name, v in self._sample(u, pts[a:a + chunk], nodal_strain).items():
                out[name][a:a + chunk] = v
        return out

    def _sample(self, u, points, nodal_strain) -> dict:
        inside, e, X, nodes = self.locate(points)
        h = np.stack([self.axes[a][e[a] + 1] - self.axes[a][e[a]] for a in range(3)])           # (3, n)
        W, dW = [], []
        for i in (0, 1):
            for j in (0, 1):
                for k in (0, 1):
                    f = [X[0] if i else 1 - X[0], X[1] if j else 1 - X[1], X[2] if k else 1 - X[2]]
                    d = [(1 if i else -1) / h[0], (1 if j else -1) / h[1], (1 if k else -1) / h[2]]
                    W.append(f[0] * f[1] * f[2])
                    dW.append(np.stack([d[0] * f[1] * f[2], f[0] * d[1] * f[2], f[0] * f[1] * d[2]]))
        W, dW = np.array(W), np.array(dW)                                                      # (8, n), (8, 3, n)
        out = {}
        for c, name in enumerate(DISPLACEMENT_COMPONENTS_3D):
            out[name] = np.sum(W * u[c::3][nodes], axis=0)
        if nodal_strain is None:
            grad = np.stack([np.sum(dW * u[c::3][nodes][:, None, :], axis=0) for c in range(3)])  # (3, 3, n)
            E = strain_from_gradient(grad)
        else:
            E = np.column_stack([np.sum(W * nodal_strain[:, k][nodes], axis=0) for k in range(6)])
        for k, name in enumerate(STRAIN_COMPONENTS_3D):
            out[name] = E[:, k]
        for name in out:
            out[name] = np.where(inside, out[name], np.nan)
        return out
