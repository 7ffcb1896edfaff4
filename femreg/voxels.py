"""Volumes on a voxel grid: the 3D image term of eq:IR on trilinear hexahedra, integrated at voxel centres.

Convention: a volume is a 3D array ``[i, j, k]`` = (axial x, lateral y, elevational z); voxel ``[i, j, k]`` has
its centre at ``origin + (i dx, j dy, k dz)`` mm.  This is the 3D form of :mod:`femreg.pixels` and
:mod:`femreg.data_term`:

* :func:`roi_mesh_3d`: a structured ``MeshHex1`` whose faces lie on voxel-cell boundaries, so every voxel centre
  lies strictly inside one element and location is arithmetic (element index and reference coordinate per voxel
  row, column and slice, :class:`VoxelGrid`).
* :class:`SplineVolume`: the tricubic B-spline interpolant (Unser 1999, doi:10.1109/79.799930; scipy.ndimage
  conventions: ``spline_filter`` with mirror boundary, 0 outside the voxel cells), its exact gradient at the
  knots (voxel centres) for eq:wfnew.
* :class:`VoxelSSDTerm`: psi = 1/2 sum_p w_p r_p^2, r_p = I_2(x_p + S + u(x_p)) - I_1(x_p + S), with the fixed
  reference gradient Gauss-Newton Hessian of eq:wfnew, ``w_p = dx dy dz`` (mm^3).  Everything runs separably on
  the tensor structure: u at the voxels is three small matrix products with the 1D hat functions, the gradient
  their transpose, and the Hessian's element sums of N_k N_l g_a g_b w factor into 1D sums of (1 - X)^2,
  X (1 - X), X^2 along each axis (the 3D form of :meth:`femreg.data_term.SSDTerm._hessian_separable`).  The warp
  of I_2 (64 spline coefficients per voxel) is one compiled pass (:func:`femreg._kernels.tricubic_grid`) or
  ``map_coordinates`` without numba.

Memory (a volume of N voxels): the per-voxel reference values and gradients are stored in single precision
(:data:`VOXEL_DTYPE`), the moving spline keeps only its padded coefficients, and the warp, u at the voxels, the
reference gradients and the NCC run in axial slabs (:data:`WARP_CHUNK`, :data:`GRADIENT_CHUNK` voxels), and weights
that only leave voxels out are a boolean mask, so a registration holds about 40 bytes per voxel beside its
temporaries (benchmarks/README.md).
"""
from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from . import _kernels
from .errors import InputError

__all__ = ["SplineVolume", "VoxelGrid", "VoxelSSDTerm", "roi_mesh_3d", "validate_volume", "validate_spacing_3d",
           "tensor_axes_3d", "hat_matrix", "DEFAULT_ELEMENT_SIZE_3D", "DEFAULT_MARGIN_3D"]

#: Default element size (axial, lateral, elevational) mm of volume registration.
DEFAULT_ELEMENT_SIZE_3D = (2.0, 2.0, 2.0)
#: Default margin removed on every side of the volume (mm): keeps x + u inside for motions up to about it.
DEFAULT_MARGIN_3D = (1.0, 1.0, 1.0)


def validate_spacing_3d(spacing, origin=(0.0, 0.0, 0.0)):
    """``(spacing, origin)`` as float arrays (3,) mm; :class:`InputError` naming the bad one
    (:func:`femreg.image.validate_spacing` with ``n=3``)."""
    from .image import validate_spacing

    return validate_spacing(spacing, origin, n=3)


def validate_volume(volume, name: str = "volume") -> np.ndarray:
    """A real, finite, non-constant, unsaturated 3D array of at least 4 voxels per axis, as float64; else
    InputError (:func:`femreg.image.validate_samples`)."""
    from .image import validate_samples

    return validate_samples(volume, name, ndim=3)


# ----------------------------------------------------------------------------------------------------------
# Mesh
# ----------------------------------------------------------------------------------------------------------

def roi_mesh_3d(shape, spacing, origin=(0.0, 0.0, 0.0), *, element_size=None, margin=None):
    """Structured trilinear hexahedral mesh (``skfem.MeshHex1``) over the volume minus ``margin`` (mm, default
    :data:`DEFAULT_MARGIN_3D`), elements of about ``element_size`` (mm, default :data:`DEFAULT_ELEMENT_SIZE_3D`)
    rounded to whole voxels; faces on voxel-cell boundaries (the 3D form of :func:`femreg.mesh.roi_mesh`)."""
    from skfem import MeshHex1

    from .mesh import _breaks

    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    h = np.broadcast_to(np.asarray(DEFAULT_ELEMENT_SIZE_3D if element_size is None else element_size, float), (3,))
    m = np.broadcast_to(np.asarray(DEFAULT_MARGIN_3D if margin is None else margin, float), (3,))
    if np.any(~np.isfinite(h)) or np.any(h <= 0):
        raise InputError(f"element_size must be > 0 mm, got {tuple(float(v) for v in h)}")
    if np.any(~np.isfinite(m)) or np.any(m < 0):
        raise InputError(f"margin must be >= 0 mm, got {tuple(float(v) for v in m)}")
    axes = []
    for a in range(3):
        n = int(shape[a])
        lo = int(np.ceil(m[a] / spacing[a] - 1e-9))
        hi = n - lo
        if hi - lo < 1:
            raise InputError(f"margin {m[a]} mm leaves no voxels along axis {a} (volume {n} voxels of "
                             f"{spacing[a]} mm)")
        b = _breaks(n, lo, hi, max(1.0, h[a] / spacing[a]))
        axes.append(origin[a] + (b - 0.5) * spacing[a])
    return MeshHex1.init_tensor(*axes)


def tensor_axes_3d(mesh):
    """``(axes, node)`` of an axis-aligned tensor hexahedral mesh: the three sorted node coordinate vectors and
    ``node[i, j, k]`` the node index at each grid position; None when ``mesh`` is not such a grid."""
    p = np.asarray(mesh.p)
    if p.shape[0] != 3:
        return None
    axes = [np.unique(p[a]) for a in range(3)]
    if np.prod([a.size for a in axes]) != p.shape[1] or np.prod([a.size - 1 for a in axes]) != mesh.t.shape[1]:
        return None
    idx = [np.searchsorted(axes[a], p[a]) for a in range(3)]
    node = -np.ones([a.size for a in axes], dtype=np.int64)
    node[idx[0], idx[1], idx[2]] = np.arange(p.shape[1])
    if (node < 0).any():
        return None
    # every element must be one grid cell: its corners span exactly one step along each axis
    ci = [idx[a][mesh.t] for a in range(3)]                     # (8, n_el) grid positions of the corners
    if any(np.any(c.max(0) - c.min(0) != 1) for c in ci):
        return None
    return axes, node


def hat_matrix(nodes, points) -> np.ndarray:
    """Dense (n_points, n_nodes) matrix of the 1D linear hats on the sorted ``nodes`` at ``points``, with
    ``(element, X)`` the cell and reference coordinate of every point (a point on an interior node takes the
    cell above it).  Points outside [nodes[0], nodes[-1]] get a zero row and element -1."""
    nodes = np.asarray(nodes, float)
    pts = np.asarray(points, float)
    e = np.clip(np.searchsorted(nodes, pts, side="right") - 1, 0, nodes.size - 2)
    X = (pts - nodes[e]) / (nodes[e + 1] - nodes[e])
    inside = (pts >= nodes[0] - 1e-12) & (pts <= nodes[-1] + 1e-12)
    P = np.zeros((pts.size, nodes.size))
    r = np.flatnonzero(inside)
    P[r, e[r]] = 1.0 - X[r]
    P[r, e[r] + 1] = X[r]
    e = np.where(inside, e, -1)
    return P, e, X


class VoxelGrid:
    """The voxel centres inside a tensor hexahedral mesh: a block ``[i0:i1, j0:j1, k0:k1]`` of the volume, and
    per axis the element index ``e[a]`` and reference coordinate ``X[a]`` of every voxel row, column, slice, the
    hat matrices ``P[a]`` (n_voxels_a, n_nodes_a) and the node grid ``node`` (n_x, n_y, n_z)."""

    def __init__(self, mesh, shape, spacing, origin):
        ta = tensor_axes_3d(mesh)
        if ta is None:
            raise InputError("volume registration needs an axis-aligned tensor hexahedral mesh (femreg.voxels."
                             "roi_mesh_3d)")
        self.mesh = mesh
        self.axes_nodes, self.node = ta
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        sl, self.coords, self.P, self.e, self.X = [], [], [], [], []
        for a in range(3):
            nodes = self.axes_nodes[a]
            c = self.origin[a] + self.spacing[a] * np.arange(self.shape[a])
            tol = 1e-9 * self.spacing[a]
            inside = np.flatnonzero((c > nodes[0] - tol) & (c < nodes[-1] + tol))
            if inside.size == 0:
                raise InputError("mesh outside the volume: no voxel centre lies inside the mesh")
            i0, i1 = int(inside[0]), int(inside[-1]) + 1
            sl.append(slice(i0, i1))
            P, e, X = hat_matrix(nodes, c[i0:i1])
            self.coords.append(c[i0:i1])
            self.P.append(P)
            self.e.append(e)
            self.X.append(X)
        self.block = tuple(sl)
        self.block_shape = tuple(s.stop - s.start for s in self.block)
        self.n_voxels = int(np.prod(self.block_shape))
        self.n_nodes = mesh.p.shape[1]
        self.node_shape = self.node.shape
        #: element index of every grid cell (i, j, k) of the node grid
        self.cell = _cell_index(mesh, self.node)

    def points(self) -> np.ndarray:
        """The voxel centres of the block, (n_voxels, 3) mm, C order."""
        X, Y, Z = np.meshgrid(*self.coords, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    def nodal_grid(self, u) -> list:
        """The three components of an interleaved nodal vector (3 n_nodes,) on the node grid."""
        u = np.asarray(u, float)
        return [u[c::3][self.node] for c in range(3)]

    def expand(self, U, rows=None) -> np.ndarray:
        """A nodal grid field (n_x, n_y, n_z) -> its trilinear interpolant at the voxels of the block (or of its
        axial ``rows``, a slice)."""
        return self.expand_rows(self.expand_yz(U), rows)

    def expand_yz(self, U) -> np.ndarray:
        """The lateral and elevational half of :meth:`expand`: (n_x, n_y, n_z) nodes -> (n_x, nc, nl)."""
        _, Py, Pz = self.P
        nx, ny, nz = U.shape
        T = (U.reshape(-1, nz) @ Pz.T).reshape(nx, ny, -1)              # (nx, ny, nl)
        return np.einsum("jb,abk->ajk", Py, T)                           # (nx, nc, nl)

    def expand_rows(self, T, rows=None) -> np.ndarray:
        """The axial half of :meth:`expand`: ``expand_yz``'s (n_x, nc, nl) -> the voxels of ``rows``."""
        Px = self.P[0] if rows is None else self.P[0][rows]
        return (Px @ T.reshape(T.shape[0], -1)).reshape((Px.shape[0],) + self.block_shape[1:])

    def contract(self, R) -> np.ndarray:
        """Transpose of :meth:`expand`: voxel values (nr, nc, nl) -> sums against every node's hat (n_x, n_y, n_z)."""
        Px, Py, Pz = self.P
        nr, nc, nl = self.block_shape
        T = (Px.T @ R.reshape(nr, -1)).reshape(-1, nc, nl)               # (nx, nc, nl)
        T = np.einsum("jb,ajk->abk", Py, T)                              # (nx, ny, nl)
        return (T.reshape(-1, nl) @ Pz).reshape(self.node_shape)

    def element_counts(self) -> np.ndarray:
        """Voxels in each element, on the cell grid (E_x, E_y, E_z): ``element_sums`` of ones, from the per-axis
        counts."""
        c = [_axis_counts(self.e[a], self.node_shape[a] - 1) for a in range(3)]
        return c[0][:, None, None] * c[1][None, :, None] * c[2][None, None, :]

    def element_sums(self, V) -> np.ndarray:
        """Sum of voxel values (nr, nc, nl) over each element's voxels, on the cell grid (E_x, E_y, E_z)."""
        out = V
        for a in range(3):
            e = self.e[a]
            starts = np.flatnonzero(np.diff(e, prepend=-2))
            s = np.add.reduceat(out, starts, axis=a, dtype=float)      # double sums of single-precision values
            full = np.zeros(out.shape[:a] + (self.node_shape[a] - 1,) + out.shape[a + 1:])
            idx = [slice(None)] * 3
            idx[a] = e[starts]
            full[tuple(idx)] = s
            out = full
        return out


def _slab_ncc(a, b, slabs) -> float:
    """:func:`femreg.image.ncc` of two equally shaped volumes, in double precision, summed slab by slab (no
    zero-mean copies of the whole volumes)."""
    n = a.size
    ma = sum(float(np.sum(a[s], dtype=float)) for s in slabs) / n
    mb = sum(float(np.sum(b[s], dtype=float)) for s in slabs) / n
    ab = aa = bb = 0.0
    for s in slabs:
        x = np.asarray(a[s], float).ravel() - ma
        y = np.asarray(b[s], float).ravel() - mb
        ab, aa, bb = ab + float(x @ y), aa + float(x @ x), bb + float(y @ y)
    d = np.sqrt(aa) * np.sqrt(bb)
    return float(ab / d) if d > 0 else 0.0


def _axis_counts(e, n_cells) -> np.ndarray:
    """Voxels of each of ``n_cells`` cells along one axis (``e`` the cell of each voxel row, -1 outside)."""
    return np.bincount(e[e >= 0], minlength=n_cells).astype(float)


def _cell_index(mesh, node) -> np.ndarray:
    """``cell[i, j, k]``: the element of the grid cell with lowest corner node[i, j, k]."""
    first = node[:-1, :-1, :-1]
    pos = np.full(mesh.p.shape[1], -1, dtype=np.int64)
    # the lowest corner of each element (smallest x, y and z at once) identifies its cell
    p = mesh.p[:, mesh.t]                                           # (3, 8, n_el)
    mins = p.min(axis=1)                                             # (3, n_el)
    is_low = np.all(np.isclose(p, mins[:, None, :]), axis=0)         # (8, n_el)
    low = mesh.t[np.argmax(is_low, axis=0), np.arange(mesh.t.shape[1])]
    pos[low] = np.arange(mesh.t.shape[1])
    cell = pos[first]
    if (cell < 0).any():
        raise InputError("mesh is not a tensor hexahedral grid")
    return cell


# ----------------------------------------------------------------------------------------------------------
# The tricubic interpolant
# ----------------------------------------------------------------------------------------------------------

class SplineVolume:
    """Tricubic B-spline interpolant of a volume on its voxel grid, zero outside the voxel cells.  ``keep_data``
    False: :attr:`data` is None (the samples are not kept beside the coefficients; a moving volume needs only
    these)."""

    def __init__(self, data, spacing, origin=(0.0, 0.0, 0.0), keep_data: bool = True):
        self.data = np.ascontiguousarray(data, dtype=float)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.shape = self.data.shape
        # the coefficients mirror-extended by 2 (as scipy does internally) so every stencil inside the voxel cells
        # is in range: prefiltered straight into the padded array's interior (one volume-sized array, not two)
        self._padded = _padded_spline_coefficients(self.data)
        self.coeffs = self._padded[2:-2, 2:-2, 2:-2]
        self._hi = np.array(self.shape, float) - 0.5
        if not keep_data:       # the interpolant needs only its coefficients (``data``: the samples, or None)
            self.data = None

    def at_index(self, idx) -> np.ndarray:
        """Values at fractional voxel indices ``idx`` (3, n); 0 outside the voxel cells."""
        idx = np.asarray(idx, float)
        v = ndimage.map_coordinates(self._padded, idx + 2.0, order=3, mode="constant", cval=0.0, prefilter=False)
        out = np.any((idx < -0.5) | (idx > self._hi[:, None]), axis=0)
        v[out] = 0.0
        return v

    def __call__(self, points) -> np.ndarray:
        """Values at ``points`` (n, 3) mm."""
        return self.at_index(((np.asarray(points, float) - self.origin) / self.spacing).T)

    def gradient(self, points, h: float = 1e-3) -> np.ndarray:
        """Gradient (n, 3) per mm at arbitrary points (central difference of the spline, step ``h`` voxels)."""
        idx = ((np.asarray(points, float) - self.origin) / self.spacing).T
        g = np.empty((idx.shape[1], 3))
        for a in range(3):
            e = np.zeros((3, 1))
            e[a] = h
            g[:, a] = (self.at_index(idx + e) - self.at_index(idx - e)) / (2 * h * self.spacing[a])
        return g

    def gradient_at_voxels(self, block):
        """Exact gradient of the interpolant at the voxel centres of ``block`` (three slices): at a knot the
        B-spline weights are (1, 4, 1) / 6 and the derivative weights (-1, 0, 1) / 2, so dI/dx = the central
        difference along x of the (1, 4, 1) / 6 smoothing along y and z of the coefficients."""
        def smooth(a, ax):
            n = a.shape[ax]
            lo, mid, hi = (np.take(a, range(k, n - 2 + k), axis=ax) for k in range(3))
            return (lo + 4.0 * mid + hi) / 6.0

        def diff(a, ax, h):
            n = a.shape[ax]
            return (np.take(a, range(2, n), axis=ax) - np.take(a, range(0, n - 2), axis=ax)) / (2.0 * h)

        shape = tuple(b.stop - b.start for b in block)
        g = [np.empty(shape) for _ in range(3)]
        # axial slabs of about GRADIENT_CHUNK voxels (each value needs only its 3 x 3 x 3 coefficients, so the
        # slabs give the values of the whole block at once with temporaries of the slab's size)
        step = max(1, GRADIENT_CHUNK // max(1, shape[1] * shape[2]))
        for r0 in range(0, shape[0], step):
            r1 = min(shape[0], r0 + step)
            # the slab plus 1 coefficient around it
            c = self._padded[(slice(block[0].start + r0 + 1, block[0].start + r1 + 3),)
                             + tuple(slice(b.start + 1, b.stop + 3) for b in block[1:])]
            g[0][r0:r1] = diff(smooth(smooth(c, 1), 2), 0, self.spacing[0])
            g[1][r0:r1] = diff(smooth(smooth(c, 0), 2), 1, self.spacing[1])
            g[2][r0:r1] = diff(smooth(smooth(c, 0), 1), 2, self.spacing[2])
        return tuple(g)


#: Storage type of the per-voxel reference values and gradients of :class:`VoxelSSDTerm` (4 of its arrays the
#: size of the volume).  Single precision: its relative rounding, 6e-8, is far below the speckle noise of RF data
#: (the residuals and every sum over voxels are formed in double precision).
VOXEL_DTYPE = np.float32
#: Voxels per slab of :meth:`SplineVolume.gradient_at_voxels`.
GRADIENT_CHUNK = 1 << 20
#: Voxels per slab of the warp (:meth:`VoxelSSDTerm.warped_moving`): u at them takes 24 bytes each.
WARP_CHUNK = 1 << 20


def _padded_spline_coefficients(data) -> np.ndarray:
    """``np.pad(ndimage.spline_filter(data, order=3, mode="mirror"), 2, mode="reflect")`` without the unpadded
    copy: the prefilter writes into the interior, then the borders are reflected one axis after the other (as
    ``np.pad`` does)."""
    out = np.empty(tuple(n + 4 for n in data.shape))
    inner = out[2:-2, 2:-2, 2:-2]
    inner[...] = data
    for ax in range(3):         # scipy's spline_filter: the 1D filter along each axis in turn, in place
        ndimage.spline_filter1d(inner, order=3, axis=ax, output=inner, mode="mirror")
    for ax in range(3):         # reflect (edge not repeated): out[1] = out[3], out[0] = out[4]; the same at the end
        n = out.shape[ax]

        def at(i):
            idx = [slice(None)] * 3
            idx[ax] = i
            return tuple(idx)

        out[at(1)], out[at(0)] = out[at(3)], out[at(4)]
        out[at(n - 2)], out[at(n - 1)] = out[at(n - 4)], out[at(n - 5)]
    return out


# ----------------------------------------------------------------------------------------------------------
# The image term
# ----------------------------------------------------------------------------------------------------------

class VoxelSSDTerm:
    """SSD image term (eq:IR, fixed reference gradient eq:wfnew) of a volume pair on a tensor hexahedral mesh.

    Parameters
    ----------
    grid : VoxelGrid
    reference, moving : SplineVolume
        Normalised I_1 and I_2.
    offset : (n_voxels, 3) mm, optional
        S at the voxels of the block (C order); None for 0.
    """

    hessian_fixed = True

    def __init__(self, grid: VoxelGrid, reference: SplineVolume, moving: SplineVolume, offset=None):
        self.grid = grid
        self.moving = moving
        self.shape = grid.block_shape
        self._isp = 1.0 / moving.spacing
        o, h = moving.origin, moving.spacing
        self._base1d = [(grid.coords[a] - o[a]) / h[a] for a in range(3)]
        if offset is None:
            self.offset = None
            self._base3d = None
            gx, gy, gz = reference.gradient_at_voxels(grid.block)
            self.ref_values = np.ascontiguousarray(reference.data[grid.block], dtype=VOXEL_DTYPE)
        else:
            S = np.asarray(offset, float).reshape(self.shape + (3,))
            self.offset = S
            pts = grid.points() + S.reshape(-1, 3)
            g = reference.gradient(pts)
            gx, gy, gz = (np.ascontiguousarray(g[:, a].reshape(self.shape)) for a in range(3))
            self.ref_values = reference(pts).reshape(self.shape).astype(VOXEL_DTYPE)
            X = np.meshgrid(*self._base1d, indexing="ij")
            self._base3d = [np.ascontiguousarray(X[a] + S[..., a] * self._isp[a]) for a in range(3)]
        self.g = tuple(np.ascontiguousarray(a, dtype=VOXEL_DTYPE) for a in (gx, gy, gz))
        self.w0 = float(np.prod(moving.spacing))        # voxel weight dx dy dz, mm^3
        self._w = None                                  # per-voxel weights once some are masked
        self._keep = None                               # or the voxels kept (weight w0; the others 0)
        self._H = None
        self._cache = (None, None)

    def fresh(self) -> "VoxelSSDTerm":
        """The same term with every voxel weighted again and no cached Hessian or residual; its reference values
        and gradients are this term's arrays (shared, read only)."""
        out = copy.copy(self)
        out._w, out._keep, out._H, out._cache = None, None, None, (None, None)
        return out

    def on_mesh(self, mesh) -> "VoxelSSDTerm":
        """:meth:`fresh` on another tensor ``mesh`` over the same voxel block (a refinement of this term's mesh,
        :mod:`femreg.volume_refine`): the reference values, gradients and offset are shared."""
        grid = VoxelGrid(mesh, self.grid.shape, self.grid.spacing, self.grid.origin)
        if grid.block != self.grid.block:
            raise InputError("the refined mesh covers other voxels than the mesh it refines")
        out = self.fresh()
        out.grid = grid
        return out

    # -- weights -------------------------------------------------------------------------------------------
    @property
    def w(self) -> np.ndarray:
        """Voxel weights (nr, nc, nl) mm^3 (0 for voxels left out)."""
        if self._keep is not None:
            return np.where(self._keep, self.w0, 0.0)
        return np.full(self.shape, self.w0) if self._w is None else self._w

    @w.setter
    def w(self, value):
        w = np.broadcast_to(np.asarray(value, float), self.shape)
        keep = w == self.w0
        # weights that only leave voxels out (w0 or 0, what mask_outside sets) are kept as a boolean mask: 1
        # byte per voxel instead of 8; w * r is then w0 * r or 0, the same values
        if np.all(keep | (w == 0.0)):
            self._w, self._keep = None, keep
        else:
            self._w, self._keep = w.copy(), None
        self._H = None
        self._cache = (None, None)

    def _weighted(self, r) -> np.ndarray:
        """w * r (per voxel)."""
        if self._keep is not None:
            return np.where(self._keep, self.w0 * r, 0.0)
        return self.w0 * r if self._w is None else self._w * r

    @property
    def n_voxels(self) -> int:
        return self.grid.n_voxels

    # -- warp ----------------------------------------------------------------------------------------------
    def displacement_at_voxels(self, u):
        """u at the voxels of the block: three (nr, nc, nl) arrays mm."""
        return [self.grid.expand(U) for U in self.grid.nodal_grid(u)]

    def _slabs(self):
        """Axial row slices of about :data:`WARP_CHUNK` voxels of the block."""
        nr, nc, nl = self.shape
        step = max(1, WARP_CHUNK // max(1, nc * nl))
        return [slice(r0, min(nr, r0 + step)) for r0 in range(0, nr, step)]

    def _positions(self, U, rows=slice(None)):
        """Fractional moving-volume indices (three arrays broadcasting to the rows' shape) of x + S + u."""
        if self._base3d is not None:
            return [self._base3d[a][rows] + U[a] * self._isp[a] for a in range(3)]
        b = self._base1d
        return [b[0][rows, None, None] + U[0] * self._isp[0], b[1][None, :, None] + U[1] * self._isp[1],
                b[2][None, None, :] + U[2] * self._isp[2]]

    def warped_moving(self, u, sub=None) -> np.ndarray:
        """I_2(x + S + u(x)) at the voxels (nr, nc, nl), minus ``sub`` when given.  Slab by slab (u at a slab's
        voxels, then its warp), so u at the voxels never exists for the whole block at once; each voxel's value
        is the same either way."""
        T = [self.grid.expand_yz(U) for U in self.grid.nodal_grid(u)]
        m = self.moving
        out = np.empty(self.shape)
        compiled = _kernels.use_compiled()
        e3 = np.empty((0, 0, 0))
        for rows in self._slabs():
            U = [self.grid.expand_rows(t, rows) for t in T]
            if compiled:
                bx, by, bz = (b[rows] for b in self._base3d) if self._base3d is not None else (e3, e3, e3)
                _kernels.tricubic_grid(m._padded, m._hi[0], m._hi[1], m._hi[2], self._base1d[0][rows],
                                       self._base1d[1], self._base1d[2], bx, by, bz, *U,
                                       self._isp[0], self._isp[1], self._isp[2],
                                       np.empty(0) if sub is None else sub[rows].reshape(-1),
                                       out[rows].reshape(-1))
                continue
            idx = np.stack([p.ravel() for p in np.broadcast_arrays(*self._positions(U, rows))])
            v = m.at_index(idx).reshape(out[rows].shape)
            out[rows] = v if sub is None else v - sub[rows]
        return out

    def outside_mask(self, u) -> np.ndarray:
        """(nr, nc, nl) bool: voxels that ``u`` maps less than 1 voxel from the first or 2 from the last sample
        of the moving volume on some axis (the spline there reads its mirror padding)."""
        T = [self.grid.expand_yz(U) for U in self.grid.nodal_grid(u)]
        out = np.zeros(self.shape, bool)
        for rows in self._slabs():
            P = self._positions([self.grid.expand_rows(t, rows) for t in T], rows)
            for a in range(3):
                out[rows] |= (P[a] < 1.0) | (P[a] > self.moving.shape[a] - 2.0)
        return out

    def residual(self, u) -> np.ndarray:
        key, val = self._cache
        if key is not None and np.array_equal(key, u):
            return val
        r = self.warped_moving(u, self.ref_values)
        self._cache = (np.array(u, copy=True), r)
        return r

    def energy(self, u) -> float:
        r = self.residual(u)
        if self._w is None and self._keep is None:
            return 0.5 * self.w0 * float(np.vdot(r, r))
        return 0.5 * float(np.vdot(self._weighted(r), r))

    def gradient(self, u) -> np.ndarray:
        """eq:wfnew (a): sum_p w_p r_p N_i(x_p) grad I_1(x_p), interleaved (3 n_nodes,)."""
        r = self.residual(u)
        wr = self._weighted(r)
        out = np.empty(3 * self.grid.n_nodes)
        node = self.grid.node.ravel()
        for a in range(3):
            out[3 * node + a] = self.grid.contract(wr * self.g[a]).ravel()
        return out

    def hessian(self, u=None) -> sp.csr_matrix:
        """Gauss-Newton Hessian with the fixed reference gradient (eq:wfnew b), assembled once (separable sums)."""
        if self._H is None:
            self._H = self._hessian_separable()
        return self._H

    def _hessian_separable(self):
        grid = self.grid
        w = self.w
        ex, ey, ez = (e for e in grid.e)
        E = tuple(s - 1 for s in grid.node_shape)
        # 1D products of two hats on each axis: (1 - X)^2, X (1 - X), X^2, as dense (E_a, n_a) matrices
        F = []
        for a in range(3):
            X, e = grid.X[a], grid.e[a]
            M = np.zeros((3, E[a], X.size))
            cols = np.arange(X.size)
            ok = e >= 0
            for p, f in enumerate(((1 - X) ** 2, X * (1 - X), X * X)):
                M[p, e[ok], cols[ok]] = f[ok]
            F.append(M)
        pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        nr, nc, nl = self.shape
        U = np.empty((3, 3, 3, 6) + E)
        for ab, (a, b) in enumerate(pairs):
            T = w * self.g[a] * self.g[b]
            for p in range(3):
                A = (F[0][p] @ T.reshape(nr, -1)).reshape(E[0], nc, nl)
                for q in range(3):
                    B = np.einsum("jb,abk->ajk", F[1][q], A)              # (E_x, E_y, nl)
                    for s in range(3):
                        U[p, q, s, ab] = (B.reshape(-1, nl) @ F[2][s].T).reshape(E)
        comp = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
        corners = np.array([(i, j, k) for i in range(2) for j in range(2) for k in range(2)])   # (8, 3)
        node = grid.node
        I, J, K = np.meshgrid(*(np.arange(n) for n in E), indexing="ij")
        cn = np.stack([node[I + c[0], J + c[1], K + c[2]].ravel() for c in corners])          # (8, n_el)
        S = corners[:, None, :] + corners[None, :, :]                                          # (8, 8, 3)
        vals = U.reshape(3, 3, 3, 6, -1)[S[:, :, None, None, 0], S[:, :, None, None, 1], S[:, :, None, None, 2],
                                         comp[None, None]]                                     # (8, 8, 3, 3, n_el)
        d = np.arange(3)
        rows = np.broadcast_to(3 * cn[:, None, None, None, :] + d[None, None, :, None, None], vals.shape)
        cols = np.broadcast_to(3 * cn[None, :, None, None, :] + d[None, None, None, :, None], vals.shape)
        n = 3 * grid.n_nodes
        return sp.coo_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(n, n)).tocsr()

    # -- per element ---------------------------------------------------------------------------------------
    def element_ncc(self, u, min_voxels: int = 8, warped=None) -> np.ndarray:
        """NCC of I_1 and the warped I_2 over each element's voxels, (n_el,) in ``mesh.t`` order (NaN where an
        element holds fewer than ``min_voxels``).  ``warped``: :meth:`warped_moving` of ``u`` if already at hand."""
        a = self.ref_values
        b = self.warped_moving(u) if warped is None else warped
        s = self.grid.element_sums
        n = self.grid.element_counts()
        with np.errstate(invalid="ignore", divide="ignore"):
            ma, mb = s(a) / n, s(b) / n
            cov = s(np.multiply(a, b, dtype=float)) / n - ma * mb
            va, vb = s(np.multiply(a, a, dtype=float)) / n - ma * ma, s(b * b) / n - mb * mb
            q = cov / np.sqrt(va * vb)
        q[n < min_voxels] = np.nan
        out = np.full(self.grid.mesh.t.shape[1], np.nan)
        out[self.grid.cell.ravel()] = q.ravel()
        return out

    def ncc(self, u=None, warped=None) -> float:
        """NCC of I_1 and I_2(x + S + u) over the voxels of the mesh (u = None: zero; ``warped``: that warp if
        already at hand)."""
        b = warped if warped is not None else self.warped_moving(np.zeros(3 * self.grid.n_nodes) if u is None else u)
        return _slab_ncc(self.ref_values, b, self._slabs())
