"""The image (data) term psi of eq:IR, integrated by the pixel midpoint rule, with the Gauss-Newton Hessian
built from the FIXED reference gradient (eq:wfnew).

    psi[u]            = 1/2 sum_p w_p r_p(u)^2,        r_p(u) = I_2(x_p + S(x_p) + u(x_p)) - I_1(x_p + S(x_p))
    D psi[u] . w      = sum_p w_p r_p(u) grad I_1(x_p + S(x_p)) . w(x_p)                       (eq:wfnew a)
    D^2 psi[u] ~ H    = sum_p w_p (N_p (x) g_p)(N_p (x) g_p)^T,  g_p = grad I_1 at x_p + S   (eq:wfnew b)

with ``w_p = dx dy`` and ``N_p`` the bilinear shape functions at pixel p.  In matrix form, with the sparse
"Jacobian" ``J`` of shape (n_pixels, 2 n_nodes), ``J[p, 2 i + a] = N_i(x_p) g_a(x_p)``:
``gradient = J^T (w r)``, ``H = J^T diag(w) J``.  H does not depend on u, so it is assembled once; only
``I_2(x + S + u)`` is re-interpolated per evaluation (cubic spline, prefiltered once).

S (``offset``) is the accumulated displacement of a sequence (eq:IR); with S = 0 this is the two-frame problem.

Speed: one Gauss-Newton iteration evaluates the residual (u at every pixel, then I_2 there) and the gradient once.
With numba (:mod:`femreg._kernels`) both are single compiled passes over the pixels: on a tensor mesh u comes from
the separable description of the pixel grid (element row/column and reference coordinate of every pixel row and
column), elsewhere from the four shape functions of each pixel; without numba, from the sparse operator ``P`` and
``map_coordinates``.  The data Hessian is assembled once: by separable row/column sums on tensor meshes, else
element by element (compiled) or as ``J^T W J``.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import _kernels
from ._kernels import element_blocks, gradient_grid, gradient_nodes, hessian_rows, warp_grid, warp_nodes
from .image import SplineImage
from .pixels import PixelQuadrature, pixel_values

__all__ = ["SSDTerm"]


class SSDTerm:
    """Sum-of-squared-differences image term on a pixel quadrature.

    Parameters
    ----------
    quad : PixelQuadrature
    reference, moving : SplineImage
        Normalised I_1 and I_2.
    offset : (m, 2) array, mm, optional
        S at the quadrature pixels (``quad.points``); None for 0.
    """

    #: The Gauss-Newton Hessian does not depend on u (eq:wfnew): ``hessian`` returns the same matrix object until
    #: the pixel weights change.
    hessian_fixed = True

    def __init__(self, quad: PixelQuadrature, reference: SplineImage, moving: SplineImage, offset=None):
        self.quad = quad
        self.moving = moving
        #: S at the quadrature pixels (m, 2) mm, or None
        self.offset = None if offset is None else np.asarray(offset, float).reshape(quad.n_pixels, 2)
        block = getattr(quad, "block", None)
        self._ref_gradient = None
        self._knots = offset is None        # I_2 at u = 0 is the pixel values (S = 0)
        self._moving_values = None
        self._inv_sp = 1.0 / moving.spacing
        o, h = moving.origin, moving.spacing
        self._bx = self._by = None
        self._bxr = self._byc = np.empty(0)
        if offset is None and block is not None:
            # the pixels are a block of the image (tensor mesh): slices instead of gathers (same values), and the
            # base positions of I_2 per row and column (the warp reads two short vectors, not two images)
            gx, gy = reference.gradient_at_pixels(block)
            self._gx, self._gy = gx.ravel(), gy.ravel()
            self.ref_values = reference.data[block].ravel()
            xr, yc = quad.axes
            self._bxr, self._byc = (xr - o[0]) / h[0], (yc - o[1]) / h[1]
        elif offset is None:
            gx, gy = reference.gradient_at_pixels()
            self._gx, self._gy = gx.ravel()[quad.index], gy.ravel()[quad.index]
            self.ref_values = reference.data.ravel()[quad.index]
            pts = quad.points
            self._bx, self._by = (pts[:, 0] - o[0]) / h[0], (pts[:, 1] - o[1]) / h[1]
        else:
            base = quad.points + self.offset
            g = reference.gradient(base)
            self._gx = np.ascontiguousarray(g[:, 0])
            self._gy = np.ascontiguousarray(g[:, 1])
            self.ref_values = reference(base)
            # Base sampling positions of I_2 in fractional pixel indices; u adds (u / spacing).
            self._bx, self._by = (base[:, 0] - o[0]) / h[0], (base[:, 1] - o[1]) / h[1]
        if getattr(quad, "weights_constant", False):     # equal pixel weights: no test of all m of them
            self._w, self._w_const = quad.weights, float(quad.weights[0]) if quad.n_pixels else None
        else:
            self.w = quad.weights
        self._J = None
        self._H = None
        self._cache_u = None
        self._cache_r = None
        self._grid = quad.location.grid
        self._empty = np.empty(0)
        if self._grid is not None:
            self._node_grid = quad.locator.node_grid          # (nx, ny) node index at each grid position

    @property
    def base_index(self):
        """Base sampling positions of I_2 in fractional pixel indices, ``(bx, by)`` each (m,): x + S at the
        quadrature pixels; the warp adds u / spacing."""
        if self._bx is None:
            nr, nc = self._bxr.size, self._byc.size
            self._bx, self._by = np.repeat(self._bxr, nc), np.tile(self._byc, nr)
        return self._bx, self._by

    def outside_mask(self, u) -> np.ndarray:
        """(m,) bool: the quadrature pixels that ``u`` (2 n_nodes,) mm maps outside the moving image -- their I_2
        sampling position x + S + u lies less than 1 pixel from its first or 2 pixels from its last sample on
        either axis (the cubic spline there reads the zero padding)."""
        quad = self.quad
        hi = (self.moving.shape[0] - 2.0, self.moving.shape[1] - 2.0)
        gr = quad.location.grid
        u = np.asarray(u, float)
        if gr is not None and _kernels.use_compiled():     # one compiled pass over the pixel grid
            G = self._node_grid
            bx, by = (self._empty, self._empty) if self._bx is None else (self._bx, self._by)
            return _kernels.outside_grid(bx, by, self._bxr, self._byc, u[0::2][G], u[1::2][G], gr.i, gr.X, gr.j,
                                         gr.Y, self._inv_sp[0], self._inv_sp[1], hi[0], hi[1],
                                         np.empty(quad.n_pixels, bool))
        out = np.zeros(quad.n_pixels, bool)
        for c, base in enumerate(self.base_index):
            idx = pixel_values(quad, u[c::2])
            idx *= self._inv_sp[c]
            idx += base
            out |= idx < 1.0
            out |= idx > hi[c]
        return out

    @property
    def _moving_at_pixels(self):
        """I_2 at the quadrature pixels (u = 0, S = 0: its knots), or None with an offset."""
        if not self._knots:
            return None
        if self._moving_values is None:
            block = getattr(self.quad, "block", None)
            self._moving_values = (self.moving.data[block].ravel() if block is not None
                                   else self.moving.data.ravel()[self.quad.index])
        return self._moving_values

    @property
    def w(self) -> np.ndarray:
        """Pixel weights (m,) mm^2 of eq:IR (0 for pixels left out, e.g. mapped outside the moving image)."""
        return self._w

    @w.setter
    def w(self, value):
        # energy, gradient and Hessian all read these weights: a change (masking) reaches all three
        self._w = np.asarray(value, float)
        w = self._w
        self._w_const = float(w[0]) if w.size and np.all(w == w[0]) else None
        self._H = None
        self._cache_u = self._cache_r = None

    @property
    def ref_gradient(self):
        """grad I_1 at the quadrature pixels (x + S), (m, 2) per mm (eq:wfnew)."""
        if self._ref_gradient is None:
            self._ref_gradient = np.column_stack([self._gx, self._gy])
        return self._ref_gradient

    @property
    def _base_idx(self):
        return np.stack(self.base_index)

    # -------------------------------------------------------------------------------------------------------
    def warped_moving(self, u):
        """I_2(x + S + u(x)) at the quadrature pixels, (m,)."""
        if self._knots and not np.any(u):
            # u = 0 and S = 0: the interpolant at its knots is the pixel value (exactly, not up to round-off)
            return self._moving_at_pixels.copy()
        if _kernels.use_compiled():
            return self._warp_compiled(u, self._empty)
        P = self.quad.P
        idx = np.empty((2, self.quad.n_pixels))
        np.multiply(P @ u[0::2], self._inv_sp[0], out=idx[0])
        np.multiply(P @ u[1::2], self._inv_sp[1], out=idx[1])
        idx += self._base_idx
        return self.moving.at_index(idx)

    def _warp_compiled(self, u, sub):
        """One compiled pass: u at the pixels, I_2 there, minus ``sub`` (``ref_values`` for the residual)."""
        m = self.moving
        hi0, hi1 = m.shape[0] - 0.5, m.shape[1] - 0.5
        ux, uy = np.ascontiguousarray(u[0::2]), np.ascontiguousarray(u[1::2])
        out = np.empty(self.quad.n_pixels)
        if self._grid is not None:
            G, gr = self._node_grid, self._grid
            bx, by = (self._empty, self._empty) if self._bx is None else (self._bx, self._by)
            return warp_grid(m._padded, hi0, hi1, bx, by, self._bxr, self._byc, ux[G], uy[G], gr.i, gr.X,
                             gr.j, gr.Y, self._inv_sp[0], self._inv_sp[1], sub, out)
        loc = self.quad.location
        bx, by = self.base_index
        return warp_nodes(m._padded, hi0, hi1, bx, by, ux, uy, loc.nodes, loc.N, self._inv_sp[0],
                          self._inv_sp[1], sub, out)

    def residual(self, u):
        """r(u) = I_2(x + S + u) - I_1(x + S), (m,); cached for the last u."""
        if self._cache_u is not None and np.array_equal(u, self._cache_u):
            return self._cache_r
        if _kernels.use_compiled() and (not self._knots or np.any(u)):
            r = self._warp_compiled(u, self.ref_values)
        else:
            r = self.warped_moving(u)
            r -= self.ref_values
        self._cache_u = np.array(u, copy=True)
        self._cache_r = r
        return r

    def energy(self, u) -> float:
        r = self.residual(u)
        if self._w_const is not None:           # equal pixel weights (always, on a pixel grid): one pass
            return 0.5 * self._w_const * float(np.dot(r, r))
        return 0.5 * float(np.dot(self.w * r, r))

    @property
    def J(self):
        """Sparse (m, 2 n_nodes) Jacobian of the residual with the fixed gradient: J[p, 2i+a] = N_i g_a."""
        if self._J is None:
            loc, g = self.quad.location, self.ref_gradient
            m, nn = self.quad.n_pixels, self.quad.n_nodes
            cols = np.empty((m, 8), dtype=np.int64)
            cols[:, 0::2] = 2 * loc.nodes
            cols[:, 1::2] = 2 * loc.nodes + 1
            vals = np.empty((m, 8))
            vals[:, 0::2] = loc.N * g[:, [0]]
            vals[:, 1::2] = loc.N * g[:, [1]]
            self._J = sp.csr_matrix((vals.ravel(), cols.ravel(), np.arange(0, 8 * m + 1, 8)), shape=(m, 2 * nn))
        return self._J

    def gradient(self, u):
        """eq:wfnew (a): sum_p w_p r_p N_i(x_p) grad I_1(x_p), interleaved (2 n_nodes,)."""
        if _kernels.use_compiled():
            r = self.residual(u)
            out = np.zeros(2 * self.quad.n_nodes)
            if self._grid is not None:
                G, gr = self._node_grid, self._grid
                Gx, Gy = np.zeros(G.shape), np.zeros(G.shape)
                gradient_grid(self.w, r, self._gx, self._gy, gr.i, gr.X, gr.j, gr.Y, Gx, Gy)
                out[2 * G.ravel()] = Gx.ravel()
                out[2 * G.ravel() + 1] = Gy.ravel()
            else:
                loc = self.quad.location
                gradient_nodes(self.w, r, self._gx, self._gy, loc.nodes, loc.N, out)
            return out
        wr = self.w * self.residual(u)
        PT = self.quad.PT
        out = np.empty(2 * self.quad.n_nodes)
        out[0::2] = PT @ (wr * self.ref_gradient[:, 0])
        out[1::2] = PT @ (wr * self.ref_gradient[:, 1])
        return out

    def _hessian_separable(self):
        """H on a tensor mesh with a full pixel sub-grid: element sums of N_k N_l g_a g_b w factor into
        row sums and column sums (the shape functions are products of 1D hats), so each element's 8 x 8 block
        costs two segmented reductions of (rows x cols) arrays instead of a (pixels x 8)^T (pixels x 8) product."""
        grid = self.quad.location.grid
        nr, nc = grid.nr, grid.nc
        i, j, X, Y = grid.i, grid.j, grid.X, grid.Y
        rs = np.flatnonzero(np.diff(i, prepend=-1))           # first row of each element row
        cs = np.flatnonzero(np.diff(j, prepend=-1))
        ei, ej = i[rs], j[cs]
        if not (np.all(np.diff(i) >= 0) and np.all(np.diff(j) >= 0)):
            return None
        fx = [(1 - X) ** 2, X * (1 - X), X * X]
        fy = [(1 - Y) ** 2, Y * (1 - Y), Y * Y]
        U = np.empty((3, 3, 3, ei.size, ej.size))
        if _kernels.use_compiled():          # axial sums in one compiled pass, then the small lateral ones
            seg = np.cumsum(np.diff(i, prepend=i[0]) > 0)
            T = hessian_rows(np.ascontiguousarray(self.w, float), self._gx, self._gy, np.array(fx), seg, ei.size, nc)
            for a in range(3):
                for p in range(3):
                    for q in range(3):
                        U[p, q, a] = np.add.reduceat(T[p, a] * fy[q][None, :], cs, axis=1)
        else:
            gx, gy = self._gx.reshape(nr, nc), self._gy.reshape(nr, nc)
            w = self.w.reshape(nr, nc)
            G = [w * gx ** 2, w * gx * gy, w * gy ** 2]   # xx, xy, yy
            for a in range(3):
                for p in range(3):
                    T = np.add.reduceat(fx[p][:, None] * G[a], rs, axis=0)
                    for q in range(3):
                        U[p, q, a] = np.add.reduceat(T * fy[q][None, :], cs, axis=1)
        # corner k: x-side sx[k], y-side sy[k]; product index of two sides: 0 (both 0), 1 (mixed), 2 (both 1)
        sx = np.array([0, 1, 1, 0])
        sy = np.array([0, 0, 1, 1])
        cn = self.quad.locator.cell_nodes()[ei[:, None], ej[None, :]].reshape(-1, 4)   # (n_el, 4)
        # entry (corner k, corner l, component a, component b, element): the product sums of the two corners'
        # sides and the (a, b) gradient product (xx, xy = yx, yy), in that order
        SX, SY = sx[:, None] + sx[None, :], sy[:, None] + sy[None, :]
        comp = np.array([[0, 1], [1, 2]])
        vals = U.reshape(3, 3, 3, -1)[SX[:, :, None, None], SY[:, :, None, None], comp[None, None], :]
        c = cn.T[:, None, None, None, :]
        d = np.arange(2)
        rows = np.broadcast_to(2 * c + d[None, None, :, None, None], vals.shape)
        cols = np.broadcast_to(2 * np.swapaxes(c, 0, 1) + d[None, None, None, :, None], vals.shape)
        n = 2 * self.quad.n_nodes
        H = sp.coo_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(n, n))
        return H.tocsr()

    def _hessian_elements(self):
        """H assembled element by element (any mesh): per-element 8 x 8 sums over its pixels, then one COO."""
        loc, mesh = self.quad.location, self.quad.mesh
        t = np.ascontiguousarray(mesh.t, dtype=np.int64)
        n_el = t.shape[1]
        S = element_blocks(self.w, self._gx, self._gy, loc.N, loc.nodes, loc.element, t, n_el)
        iu = np.triu_indices(4, 1)
        S[:, iu[1], iu[0]] = S[:, iu[0], iu[1]]                  # (l, k) = (k, l): the sums are symmetric
        B = np.empty((n_el, 4, 2, 4, 2))                          # [e, k, a, l, b] = sum w N_k N_l g_a g_b
        B[:, :, 0, :, 0] = S[..., 0]
        B[:, :, 0, :, 1] = S[..., 1]
        B[:, :, 1, :, 0] = S[..., 1]
        B[:, :, 1, :, 1] = S[..., 2]
        B = B.reshape(n_el, 8, 8)
        dof = np.empty((n_el, 8), dtype=np.int64)
        dof[:, 0::2] = 2 * t.T
        dof[:, 1::2] = 2 * t.T + 1
        rows = np.broadcast_to(dof[:, :, None], B.shape).ravel()
        cols = np.broadcast_to(dof[:, None, :], B.shape).ravel()
        n = 2 * self.quad.n_nodes
        return sp.coo_matrix((B.ravel(), (rows, cols)), shape=(n, n)).tocsr()

    def hessian(self, u=None):
        """Gauss-Newton Hessian with the fixed reference gradient (independent of u; assembled once)."""
        if self._H is None and self.quad.location.grid is not None:
            self._H = self._hessian_separable()
        if self._H is None and _kernels.use_compiled():
            self._H = self._hessian_elements()
        if self._H is None:
            Jw = self.J.multiply(np.sqrt(self.w)[:, None]).tocsr() if not np.all(self.w == self.w[0]) else None
            if Jw is None:
                H = (self.J.T @ self.J) * float(self.w[0])
            else:
                H = Jw.T @ Jw
            H = sp.csr_matrix(H)
            H.sum_duplicates()
            self._H = H
        return self._H
