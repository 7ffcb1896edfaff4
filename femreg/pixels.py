"""Point location in a quad mesh and the pixel-quadrature coupling of the image term (eq:IR).

Every pixel centre inside the mesh is mapped to (element, reference coordinates) by the inverse bilinear map;
the image term is then integrated by the midpoint rule at pixel centres (weight dx * dy each), as in the paper's
appendix "Numerical Integration".  The pixel->node operator ``P`` (sparse, (n_pixels_inside, n_nodes), four
bilinear shape-function values per row) interpolates nodal fields to pixels: ``ux_pix = P @ u[0::2]``.

* Axis-aligned tensor meshes (the default ROI mesh): location is arithmetic (``searchsorted`` on each axis).
* Any other quad mesh: a KD-tree on element centroids proposes candidates, a vectorised Newton iteration
  inverts the bilinear map of each candidate, the first candidate with reference coordinates in [0, 1]^2 wins.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .mesh import tensor_structure

__all__ = ["Location", "PointLocator", "PixelQuadrature"]

# Reference square [0, 1]^2 of skfem's ElementQuad1; local node k sits at _REF[k].
_REF = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _phi(X, Y):
    """Bilinear shape functions (n, 4) and their reference gradients (n, 4, 2), skfem's ElementQuad1 order."""
    phi = np.stack([(1 - X) * (1 - Y), X * (1 - Y), X * Y, (1 - X) * Y], axis=1)
    dX = np.stack([-(1 - Y), 1 - Y, Y, -Y], axis=1)
    dY = np.stack([-(1 - X), -X, X, 1 - X], axis=1)
    return phi, np.stack([dX, dY], axis=2)


@dataclass
class Location:
    """Where points lie in a mesh.  ``inside`` (n,) bool; for the inside points only (m = inside.sum()):
    ``element`` (m,), ``nodes`` (m, 4) global node indices, ``N`` (m, 4) shape-function values,
    ``dN`` (m, 4, 2) physical gradients [d/dx, d/dy] per mm."""

    inside: np.ndarray
    element: np.ndarray
    nodes: np.ndarray
    N: np.ndarray
    dN: np.ndarray

    def operator(self, n_nodes: int) -> sp.csr_matrix:
        """Sparse (m, n_nodes) interpolation operator: row k = shape functions of point k."""
        m = self.nodes.shape[0]
        indptr = np.arange(0, 4 * m + 1, 4)
        return sp.csr_matrix((self.N.ravel(), self.nodes.ravel(), indptr), shape=(m, n_nodes))

    def gradient_operators(self, n_nodes: int):
        """Sparse (m, n_nodes) operators Dx, Dy: d/dx and d/dy of a nodal scalar field at the points."""
        m = self.nodes.shape[0]
        indptr = np.arange(0, 4 * m + 1, 4)
        return tuple(sp.csr_matrix((self.dN[:, :, a].ravel(), self.nodes.ravel(), indptr), shape=(m, n_nodes))
                     for a in range(2))


class PointLocator:
    """Locate points of the plane in a ``MeshQuad1`` (arithmetic on tensor meshes, KD-tree + Newton otherwise)."""

    def __init__(self, mesh, tol: float = 1e-10):
        self.mesh = mesh
        self.tol = tol
        self.tensor = tensor_structure(mesh)
        self._tree = None

    # -- structured ---------------------------------------------------------------------------------------
    def _locate_tensor(self, pts):
        xs, ys, cell = self.tensor
        x, y = pts[:, 0], pts[:, 1]
        hx, hy = xs[-1] - xs[0], ys[-1] - ys[0]
        inside = ((x >= xs[0] - self.tol * hx) & (x <= xs[-1] + self.tol * hx)
                  & (y >= ys[0] - self.tol * hy) & (y <= ys[-1] + self.tol * hy))
        x, y = x[inside], y[inside]
        i = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, xs.size - 2)
        j = np.clip(np.searchsorted(ys, y, side="right") - 1, 0, ys.size - 2)
        e = cell[i, j]
        nodes = self.mesh.t[:, e].T                   # (m, 4), in the element's own local order
        hx = (xs[i + 1] - xs[i])[:, None]
        hy = (ys[j + 1] - ys[j])[:, None]
        # orientation-free bilinear weights: node k at the right (top) side gets X (Y), else 1 - X (1 - Y)
        right = self.mesh.p[0][nodes] > (xs[i] + 0.5 * hx[:, 0])[:, None]
        top = self.mesh.p[1][nodes] > (ys[j] + 0.5 * hy[:, 0])[:, None]
        X = ((x - xs[i]) / hx[:, 0])[:, None]
        Y = ((y - ys[j]) / hy[:, 0])[:, None]
        wx = np.where(right, X, 1.0 - X)
        wy = np.where(top, Y, 1.0 - Y)
        N = wx * wy
        dN = np.empty(N.shape + (2,))
        dN[:, :, 0] = np.where(right, 1.0, -1.0) / hx * wy
        dN[:, :, 1] = np.where(top, 1.0, -1.0) / hy * wx
        return Location(inside, e, nodes, N, dN)

    # -- general ------------------------------------------------------------------------------------------
    def _newton(self, pts, e, iters: int = 12):
        """Invert the bilinear map of elements e at pts; returns X, Y (reference) for each pair."""
        P = self.mesh.p[:, self.mesh.t[:, e]]          # (2, 4, n)
        X = np.full(len(e), 0.5)
        Y = np.full(len(e), 0.5)
        for _ in range(iters):
            phi, dphi = _phi(X, Y)
            xm = np.einsum("dkn,nk->nd", P, phi)
            J = np.einsum("dkn,nkr->ndr", P, dphi)     # dx_d / dX_r
            r = pts - xm
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            det = np.where(np.abs(det) > 0, det, 1e-300)
            dX = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            dY = (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
            X = X + dX
            Y = Y + dY
            if max(np.abs(dX).max(initial=0), np.abs(dY).max(initial=0)) < 1e-14:
                break
        phi, _ = _phi(X, Y)
        res = np.linalg.norm(pts - np.einsum("dkn,nk->nd", P, phi), axis=1)
        return X, Y, res

    def _locate_general(self, pts, k: int = 8):
        from scipy.spatial import cKDTree

        mesh = self.mesh
        if self._tree is None:
            self._tree = cKDTree(mesh.p[:, mesh.t].mean(axis=1).T)
            self._size = float(np.ptp(mesh.p, axis=1).max())
        k = min(k, mesh.t.shape[1])
        _, cand = self._tree.query(pts, k=k)
        cand = cand.reshape(len(pts), k)
        n = len(pts)
        elem = np.full(n, -1, dtype=np.int64)
        X = np.zeros(n)
        Y = np.zeros(n)
        todo = np.arange(n)
        tol = 1e-9
        for c in range(k):
            if todo.size == 0:
                break
            e = cand[todo, c]
            Xc, Yc, res = self._newton(pts[todo], e)
            ok = ((Xc >= -tol) & (Xc <= 1 + tol) & (Yc >= -tol) & (Yc <= 1 + tol) & np.isfinite(Xc + Yc)
                  & (res <= 1e-9 * self._size))
            elem[todo[ok]] = e[ok]
            X[todo[ok]] = np.clip(Xc[ok], 0, 1)
            Y[todo[ok]] = np.clip(Yc[ok], 0, 1)
            todo = todo[~ok]
        inside = elem >= 0
        return inside, elem[inside], X[inside], Y[inside]

    def locate(self, points) -> Location:
        """Locate ``points`` (n, 2) mm; returns a :class:`Location`."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if self.tensor is not None:
            return self._locate_tensor(pts)
        inside, e, X, Y = self._locate_general(pts)
        nodes = self.mesh.t[:, e].T
        phi, dphi = _phi(X, Y)
        # physical gradients: dN/dx = J^{-T} dN/dX, J_dr = sum_k p_d(node k) dphi_k/dX_r
        px = self.mesh.p[0][nodes]                      # (m, 4)
        py = self.mesh.p[1][nodes]
        J00 = np.sum(px * dphi[:, :, 0], axis=1)
        J01 = np.sum(px * dphi[:, :, 1], axis=1)
        J10 = np.sum(py * dphi[:, :, 0], axis=1)
        J11 = np.sum(py * dphi[:, :, 1], axis=1)
        det = J00 * J11 - J01 * J10
        dN = np.empty_like(dphi)
        dN[:, :, 0] = (dphi[:, :, 0] * J11[:, None] - dphi[:, :, 1] * J10[:, None]) / det[:, None]
        dN[:, :, 1] = (-dphi[:, :, 0] * J01[:, None] + dphi[:, :, 1] * J00[:, None]) / det[:, None]
        return Location(inside, e, nodes, phi, dN)


class PixelQuadrature:
    """Pixel-centre midpoint quadrature of the image term on a mesh.

    Parameters
    ----------
    mesh : skfem.MeshQuad1
    shape : (n_axial, n_lateral)
    spacing, origin : (2,) mm

    Attributes
    ----------
    index : (m,) int
        Flat (C-order) indices of the pixels whose centres lie in the mesh.
    points : (m, 2) float, mm
        Their centres.
    weights : (m,) float, mm^2
        Midpoint-rule weights, dx * dy each.
    P : (m, n_nodes) csr
        Pixel->node interpolation operator.
    location : Location
    """

    def __init__(self, mesh, shape, spacing, origin, locator: PointLocator | None = None):
        self.mesh = mesh
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.locator = locator or PointLocator(mesh)
        lo = mesh.p.min(axis=1)
        hi = mesh.p.max(axis=1)
        # only pixels in the mesh's bounding box are candidates
        i0 = max(0, int(np.floor((lo[0] - self.origin[0]) / self.spacing[0])))
        i1 = min(self.shape[0] - 1, int(np.ceil((hi[0] - self.origin[0]) / self.spacing[0])))
        j0 = max(0, int(np.floor((lo[1] - self.origin[1]) / self.spacing[1])))
        j1 = min(self.shape[1] - 1, int(np.ceil((hi[1] - self.origin[1]) / self.spacing[1])))
        ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        ii, jj = ii.ravel(), jj.ravel()
        pts = np.column_stack([self.origin[0] + ii * self.spacing[0], self.origin[1] + jj * self.spacing[1]])
        loc = self.locator.locate(pts)
        self.location = loc
        self.index = (ii * self.shape[1] + jj)[loc.inside]
        self.points = pts[loc.inside]
        self.ij = (ii[loc.inside], jj[loc.inside])
        self.weights = np.full(self.index.size, self.spacing[0] * self.spacing[1])
        self.n_nodes = mesh.p.shape[1]
        self.P = loc.operator(self.n_nodes)

    @property
    def n_pixels(self) -> int:
        return int(self.index.size)

    def interpolate(self, u: np.ndarray) -> np.ndarray:
        """Nodal vector u (2 n_nodes,) (interleaved) -> pixel displacements (m, 2) mm."""
        return np.column_stack([self.P @ u[0::2], self.P @ u[1::2]])
