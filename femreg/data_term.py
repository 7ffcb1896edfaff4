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
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .image import SplineImage
from .pixels import PixelQuadrature

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

    def __init__(self, quad: PixelQuadrature, reference: SplineImage, moving: SplineImage, offset=None):
        self.quad = quad
        self.moving = moving
        pts = quad.points
        if offset is None:
            gx, gy = reference.gradient_at_pixels()
            g = np.column_stack([gx.ravel()[quad.index], gy.ravel()[quad.index]])
            base = pts
            # I_1 through the same interpolant as I_2 (equal to the pixel values up to round-off), so that
            # identical frames give a residual of exactly zero
            self.ref_values = reference(base)
        else:
            base = pts + np.asarray(offset, float).reshape(pts.shape)
            g = reference.gradient(base)
            self.ref_values = reference(base)
        self.ref_gradient = g
        # Base sampling positions of I_2 in fractional pixel indices; u adds (u / spacing).
        self._base_idx = ((base - moving.origin) / moving.spacing).T.copy()
        self._inv_sp = 1.0 / moving.spacing
        w = quad.weights
        self.w = w
        loc = quad.location
        m = quad.n_pixels
        nn = quad.n_nodes
        cols = np.empty((m, 8), dtype=np.int64)
        cols[:, 0::2] = 2 * loc.nodes
        cols[:, 1::2] = 2 * loc.nodes + 1
        vals = np.empty((m, 8))
        vals[:, 0::2] = loc.N * g[:, [0]]
        vals[:, 1::2] = loc.N * g[:, [1]]
        self.J = sp.csr_matrix((vals.ravel(), cols.ravel(), np.arange(0, 8 * m + 1, 8)), shape=(m, 2 * nn))
        self._H = None
        self._cache_u = None
        self._cache_r = None
        self._idx = np.empty_like(self._base_idx)
        self._buf = np.empty(m)

    # -------------------------------------------------------------------------------------------------------
    def warped_moving(self, u):
        """I_2(x + S + u(x)) at the quadrature pixels, (m,)."""
        P = self.quad.P
        np.multiply(P @ u[0::2], self._inv_sp[0], out=self._idx[0])
        np.multiply(P @ u[1::2], self._inv_sp[1], out=self._idx[1])
        self._idx += self._base_idx
        return self.moving.at_index(self._idx)

    def residual(self, u):
        """r(u) = I_2(x + S + u) - I_1(x + S), (m,); cached for the last u."""
        if self._cache_u is not None and np.array_equal(u, self._cache_u):
            return self._cache_r
        r = self.warped_moving(u)
        r -= self.ref_values
        self._cache_u = np.array(u, copy=True)
        self._cache_r = r
        return r

    def energy(self, u) -> float:
        r = self.residual(u)
        return 0.5 * float(np.dot(self.w * r, r))

    def gradient(self, u):
        r = self.residual(u)
        return self.J.T @ (self.w * r)

    def hessian(self, u=None):
        """Gauss-Newton Hessian with the fixed reference gradient (independent of u; assembled once)."""
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
