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
    grid: dict | None = None

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
    def _canonical(self):
        """Per tensor cell (i, j) its nodes in skfem reference order (x0,y0), (x1,y0), (x1,y1), (x0,y1), so that
        the shape functions are :func:`_phi` of (X, Y) = ((x - x0)/hx, (y - y0)/hy) whatever the mesh's own
        local node order (init_tensor, for one, numbers its quads clockwise)."""
        if getattr(self, "_cn", None) is None:
            xs, ys, _ = self.tensor
            p = self.mesh.p
            G = np.empty((xs.size, ys.size), dtype=np.int64)
            G[np.searchsorted(xs, p[0]), np.searchsorted(ys, p[1])] = np.arange(p.shape[1])
            self._cn = np.stack([G[:-1, :-1], G[1:, :-1], G[1:, 1:], G[:-1, 1:]], axis=-1)
        return self._cn

    def _axis(self, v, breaks):
        span = breaks[-1] - breaks[0]
        inside = (v >= breaks[0] - self.tol * span) & (v <= breaks[-1] + self.tol * span)
        i = np.clip(np.searchsorted(breaks, v, side="right") - 1, 0, breaks.size - 2)
        h = breaks[i + 1] - breaks[i]
        return inside, i, (v - breaks[i]) / h, h

    def _locate_tensor(self, pts):
        xs, ys, cell = self.tensor
        inx, i, X, hx = self._axis(pts[:, 0], xs)
        iny, j, Y, hy = self._axis(pts[:, 1], ys)
        inside = inx & iny
        i, j, X, Y, hx, hy = i[inside], j[inside], X[inside], Y[inside], hx[inside], hy[inside]
        N, dphi = _phi(X, Y)
        dphi[:, :, 0] /= hx[:, None]
        dphi[:, :, 1] /= hy[:, None]
        return Location(inside, cell[i, j], self._canonical()[i, j], N, dphi)

    def locate_grid(self, xa, ya) -> Location:
        """Locate the tensor grid of points (xa[i], ya[j]) (C order).  Separable and fast on tensor meshes."""
        xa = np.asarray(xa, float)
        ya = np.asarray(ya, float)
        if self.tensor is None:
            X, Y = np.meshgrid(xa, ya, indexing="ij")
            return self.locate(np.column_stack([X.ravel(), Y.ravel()]))
        xs, ys, cell = self.tensor
        inx, i, X, hx = self._axis(xa, xs)
        iny, j, Y, hy = self._axis(ya, ys)
        inside = (inx[:, None] & iny[None, :]).ravel()
        i, X, hx = i[inx], X[inx], hx[inx]
        j, Y, hy = j[iny], Y[iny], hy[iny]
        AX = np.stack([1 - X, X, X, 1 - X], axis=1)           # (nr, 4)
        AY = np.stack([1 - Y, 1 - Y, Y, Y], axis=1)           # (nc, 4)
        dAX = np.array([-1.0, 1.0, 1.0, -1.0])[None, :] / hx[:, None]
        dAY = np.array([-1.0, -1.0, 1.0, 1.0])[None, :] / hy[:, None]
        N = (AX[:, None, :] * AY[None, :, :]).reshape(-1, 4)
        dN = np.empty(N.shape + (2,))
        dN[:, :, 0] = (dAX[:, None, :] * AY[None, :, :]).reshape(-1, 4)
        dN[:, :, 1] = (AX[:, None, :] * dAY[None, :, :]).reshape(-1, 4)
        nodes = self._canonical()[i[:, None], j[None, :]].reshape(-1, 4)
        loc = Location(inside, cell[i[:, None], j[None, :]].ravel(), nodes, N, dN)
        # separable description (rows x cols of inside points), used for fast pixel-quadrature assembly
        loc.grid = dict(i=i, j=j, X=X, Y=Y, nr=int(i.size), nc=int(j.size))
        return loc

    # -- general ------------------------------------------------------------------------------------------
    def _newton(self, pts, e, iters: int = 12):
        """Invert the bilinear map of elements e at pts; returns X, Y (reference) and the residual (mm)."""
        t = self.mesh.t[:, e]
        px = self.mesh.p[0][t]                          # (4, n)
        py = self.mesh.p[1][t]
        # x(X, Y) = a0 + a1 X + a2 Y + a3 X Y  (skfem ElementQuad1 node order)
        ax = (px[0], px[1] - px[0], px[3] - px[0], px[0] - px[1] + px[2] - px[3])
        ay = (py[0], py[1] - py[0], py[3] - py[0], py[0] - py[1] + py[2] - py[3])
        x, y = pts[:, 0], pts[:, 1]
        X = np.full(len(e), 0.5)
        Y = np.full(len(e), 0.5)
        for _ in range(iters):
            rx = x - (ax[0] + ax[1] * X + ax[2] * Y + ax[3] * X * Y)
            ry = y - (ay[0] + ay[1] * X + ay[2] * Y + ay[3] * X * Y)
            j00, j01 = ax[1] + ax[3] * Y, ax[2] + ax[3] * X
            j10, j11 = ay[1] + ay[3] * Y, ay[2] + ay[3] * X
            det = j00 * j11 - j01 * j10
            det = np.where(det != 0, det, 1e-300)
            dX = (j11 * rx - j01 * ry) / det
            dY = (-j10 * rx + j00 * ry) / det
            X += dX
            Y += dY
            if max(np.abs(dX).max(initial=0), np.abs(dY).max(initial=0)) < 1e-13:
                break
        rx = x - (ax[0] + ax[1] * X + ax[2] * Y + ax[3] * X * Y)
        ry = y - (ay[0] + ay[1] * X + ay[2] * Y + ay[3] * X * Y)
        return X, Y, np.hypot(rx, ry)

    def _locate_general(self, pts, k: int = 8):
        from scipy.spatial import cKDTree

        mesh = self.mesh
        if self._tree is None:
            self._tree = cKDTree(mesh.p[:, mesh.t].mean(axis=1).T)
            self._size = float(np.ptp(mesh.p, axis=1).max())
        n = len(pts)
        elem = np.full(n, -1, dtype=np.int64)
        X = np.zeros(n)
        Y = np.zeros(n)
        tol = 1e-9
        todo = np.arange(n)
        k = min(k, mesh.t.shape[1])
        # nearest centroid first (resolves almost every point), then up to k candidates for the rest
        for kk in sorted({1, k}):
            if todo.size == 0:
                break
            _, cand = self._tree.query(pts[todo], k=kk)
            cand = np.asarray(cand).reshape(todo.size, kk)
            for c in range(kk if kk == 1 else 1, kk) if kk > 1 else range(1):
                if todo.size == 0:
                    break
                e = cand[:, c]
                Xc, Yc, res = self._newton(pts[todo], e)
                ok = ((Xc >= -tol) & (Xc <= 1 + tol) & (Yc >= -tol) & (Yc <= 1 + tol) & np.isfinite(Xc + Yc)
                      & (res <= 1e-9 * self._size))
                elem[todo[ok]] = e[ok]
                X[todo[ok]] = np.clip(Xc[ok], 0, 1)
                Y[todo[ok]] = np.clip(Yc[ok], 0, 1)
                todo, cand = todo[~ok], cand[~ok]
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
        xa = self.origin[0] + np.arange(i0, i1 + 1) * self.spacing[0]
        ya = self.origin[1] + np.arange(j0, j1 + 1) * self.spacing[1]
        pts = np.column_stack([xa[ii - i0], ya[jj - j0]])
        loc = self.locator.locate_grid(xa, ya)
        self.location = loc
        self.index = (ii * self.shape[1] + jj)[loc.inside]
        self.points = pts[loc.inside]
        self.ij = (ii[loc.inside], jj[loc.inside])
        self.weights = np.full(self.index.size, self.spacing[0] * self.spacing[1])
        self.n_nodes = mesh.p.shape[1]
        self.P = loc.operator(self.n_nodes)
        self.PT = self.P.T.tocsr()

    @property
    def n_pixels(self) -> int:
        return int(self.index.size)

    def interpolate(self, u: np.ndarray) -> np.ndarray:
        """Nodal vector u (2 n_nodes,) (interleaved) -> pixel displacements (m, 2) mm."""
        return np.column_stack([self.P @ u[0::2], self.P @ u[1::2]])
