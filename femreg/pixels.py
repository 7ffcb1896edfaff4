"""Point location in a quad mesh and the pixel-quadrature coupling of the image term (eq:IR).

Every pixel centre inside the mesh is mapped to (element, reference coordinates) by the inverse bilinear map;
the image term is then integrated by the midpoint rule at pixel centres (weight dx * dy each), as in the paper's
appendix "Numerical Integration".  The pixel->node operator ``P`` (sparse, (n_pixels_inside, n_nodes), four
bilinear shape-function values per row) interpolates nodal fields to pixels: ``ux_pix = P @ u[0::2]``.

* Axis-aligned tensor meshes (the default ROI mesh): location is arithmetic (``searchsorted`` on each axis).
* Logically structured meshes (the topology of ``MeshQuad1.init_tensor``, nodes anywhere, e.g. the ROI mesh
  moved by the accumulated displacement S_k in :func:`femreg.track`): a first guess of each point's cell from
  the mean node position of every grid row and column, then a vectorised Newton inversion of that cell's bilinear
  map and a walk to the neighbouring cell the reference coordinates point to, a few steps; points not settled
  that way go to the general search.  The compiled walk (:mod:`femreg._kernels`) is several times faster than
  its numpy twin and the general search alone (benchmarks/README.md, "Timings").
* Any other quad mesh: a KD-tree on element centroids proposes candidates, a vectorised Newton iteration
  inverts the bilinear map of each candidate, the first candidate with reference coordinates in [0, 1]^2 wins.

All three accept a point when its reference coordinates lie in [0, 1]^2 up to 1e-9 and the bilinear map reproduces
it to 1e-9 of the mesh size; they differ only in which element a point on a shared edge is given to (the shape
function values, hence the interpolated fields, agree to round-off).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import _kernels
from .mesh import tensor_node_grid, tensor_structure

__all__ = ["Location", "AxisLocation", "GridLocation", "PointLocator", "PixelQuadrature", "logical_grid",
           "pixel_values"]

# Reference square [0, 1]^2 of skfem's ElementQuad1; local node k sits at _REF[k].
_REF = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _phi(X, Y):
    """Bilinear shape functions (n, 4) and their reference gradients (n, 4, 2), skfem's ElementQuad1 order."""
    phi = np.stack([(1 - X) * (1 - Y), X * (1 - Y), X * Y, (1 - X) * Y], axis=1)
    dX = np.stack([-(1 - Y), 1 - Y, Y, -Y], axis=1)
    dY = np.stack([-(1 - X), -X, X, 1 - X], axis=1)
    return phi, np.stack([dX, dY], axis=2)


@dataclass(frozen=True)
class AxisLocation:
    """The samples of one axis of a tensor grid of points, located in the breaks (node coordinates) of a tensor
    mesh along that axis: for the ``m`` samples inside, the interval ``cell`` (m,) int holding each, its reference
    coordinate ``local`` (m,) in [0, 1] and the interval length ``h`` (m,) mm; ``index`` (m,) int: which of the
    axis's samples they are (consecutive)."""

    cell: np.ndarray
    local: np.ndarray
    h: np.ndarray
    index: np.ndarray

    @property
    def size(self) -> int:
        return int(self.index.size)


@dataclass(frozen=True)
class GridLocation:
    """Separable location of a tensor grid of points in a tensor mesh: one :class:`AxisLocation` per axis (axial
    first).  The inside points are the C-order grid of the axes' inside samples; a cell of the mesh is the tuple
    of the axes' intervals.  Two axes today (quads on a pixel grid); the same description holds for a third axis
    (hexahedra on voxels), for refined tensor meshes (any breaks) and for samples along the rays of a convex probe
    where the mesh is a tensor mesh in the probe's (depth, line) coordinates.

    ``i``, ``X``, ``j``, ``Y``: the axial and lateral intervals and reference coordinates; ``rows``, ``cols``:
    which point-grid rows and columns are inside; ``nr``, ``nc`` their numbers."""

    axes: tuple

    @property
    def shape(self) -> tuple:
        return tuple(a.size for a in self.axes)

    i = property(lambda self: self.axes[0].cell)
    X = property(lambda self: self.axes[0].local)
    hx = property(lambda self: self.axes[0].h)
    rows = property(lambda self: self.axes[0].index)
    nr = property(lambda self: self.axes[0].size)
    j = property(lambda self: self.axes[1].cell)
    Y = property(lambda self: self.axes[1].local)
    hy = property(lambda self: self.axes[1].h)
    cols = property(lambda self: self.axes[1].index)
    nc = property(lambda self: self.axes[1].size)


class Location:
    """Where points lie in a mesh.  ``inside`` (n,) bool; for the inside points only (m = inside.sum()):
    ``element`` (m,), ``nodes`` (m, 4) global node indices, ``N`` (m, 4) shape-function values,
    ``dN`` (m, 4, 2) physical gradients [d/dx, d/dy] per mm.

    ``grid`` (tensor meshes and a tensor grid of points, :meth:`PointLocator.locate_grid`): the separable
    description, a :class:`GridLocation` (the inside points are the C-order grid of ``nr`` rows, element row ``i``
    and reference coordinate ``X`` each, by ``nc`` columns, ``j`` and ``Y``), else None.  Per-point arrays given
    as None are built by ``fill[name]()`` when first used (the image term needs only ``grid``).
    """

    def __init__(self, inside, element=None, nodes=None, N=None, dN=None, grid: GridLocation | None = None,
                 fill: dict | None = None):
        self.inside = inside
        self._element, self._nodes, self._N, self._dN = element, nodes, N, dN
        self.grid = grid
        self._fill = dict(fill or {})

    def _get(self, name):
        if getattr(self, name) is None and name in self._fill:
            setattr(self, name, self._fill.pop(name)())
        return getattr(self, name)

    element = property(lambda self: self._get("_element"))
    nodes = property(lambda self: self._get("_nodes"))
    N = property(lambda self: self._get("_N"))
    dN = property(lambda self: self._get("_dN"))

    def operator(self, n_nodes: int) -> sp.csr_matrix:
        """Sparse (m, n_nodes) interpolation operator: row k = shape functions of point k."""
        m = self.nodes.shape[0]
        indptr = np.arange(0, 4 * m + 1, 4)
        return sp.csr_matrix((self.N.ravel(), self.nodes.ravel(), indptr), shape=(m, n_nodes))


def _physical_gradients(mesh, nodes, dphi):
    """dN/dx = J^{-T} dN/dX with J_dr = sum_k p_d(node k) dphi_k/dX_r; ``nodes`` (m, 4), ``dphi`` (m, 4, 2)."""
    px = mesh.p[0][nodes]                      # (m, 4)
    py = mesh.p[1][nodes]
    J00 = np.sum(px * dphi[:, :, 0], axis=1)
    J01 = np.sum(px * dphi[:, :, 1], axis=1)
    J10 = np.sum(py * dphi[:, :, 0], axis=1)
    J11 = np.sum(py * dphi[:, :, 1], axis=1)
    det = J00 * J11 - J01 * J10
    dN = np.empty_like(dphi)
    dN[:, :, 0] = (dphi[:, :, 0] * J11[:, None] - dphi[:, :, 1] * J10[:, None]) / det[:, None]
    dN[:, :, 1] = (-dphi[:, :, 0] * J01[:, None] + dphi[:, :, 1] * J00[:, None]) / det[:, None]
    return dN


def _invert_bilinear(pts, px, py, iters: int = 12):
    """Newton inversion of x(X, Y) = a0 + a1 X + a2 Y + a3 X Y for corners ``px, py`` (4, n) in skfem's
    ElementQuad1 reference order (0,0), (1,0), (1,1), (0,1).  Returns X, Y and the residual |x(X, Y) - pts| (mm)."""
    ax = (px[0], px[1] - px[0], px[3] - px[0], px[0] - px[1] + px[2] - px[3])
    ay = (py[0], py[1] - py[0], py[3] - py[0], py[0] - py[1] + py[2] - py[3])
    x, y = pts[:, 0], pts[:, 1]
    X = np.full(x.shape, 0.5)
    Y = np.full(x.shape, 0.5)
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


def logical_grid(mesh):
    """If ``mesh`` has the connectivity of ``MeshQuad1.init_tensor`` (whatever its node positions), return
    ``(G, cell, cn)``: ``G[a, b]`` the node at grid position (a, b), ``cell[a, b]`` the element of grid cell
    (a, b), ``cn[a, b]`` its 4 nodes in skfem reference order (a, b), (a+1, b), (a+1, b+1), (a, b+1); else None."""
    from skfem import MeshQuad1

    n, n_el = mesh.p.shape[1], mesh.t.shape[1]
    s = n - n_el + 1                            # nx + ny, from nx ny = n and (nx - 1)(ny - 1) = n_el
    disc = s * s - 4 * n
    if n_el < 1 or disc < 0:
        return None
    r = int(round(np.sqrt(disc)))
    if r * r != disc or (s + r) % 2:
        return None
    for nx in sorted({(s + r) // 2, (s - r) // 2}):
        ny = s - nx
        if nx < 2 or ny < 2:
            continue
        ref = MeshQuad1.init_tensor(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
        if ref.t.shape == mesh.t.shape and np.array_equal(ref.t, mesh.t):
            a, b = ref.p.astype(np.int64)
            G = np.empty((nx, ny), dtype=np.int64)
            G[a, b] = np.arange(n)
            corners = ref.p[:, ref.t].min(axis=1).astype(np.int64)      # (2, n_el) lower-left grid position
            cell = np.empty((nx - 1, ny - 1), dtype=np.int64)
            cell[corners[0], corners[1]] = np.arange(n_el)
            cn = np.stack([G[:-1, :-1], G[1:, :-1], G[1:, 1:], G[:-1, 1:]], axis=-1)
            return G, cell, cn
    return None


class PointLocator:
    """Locate points of the plane in a ``MeshQuad1``: arithmetic on tensor meshes, a Newton walk on logically
    structured ones, KD-tree + Newton otherwise (see the module docstring)."""

    def __init__(self, mesh, tol: float = 1e-10):
        self.mesh = mesh
        self.tol = tol
        self.tensor = tensor_structure(mesh)
        self._logical = False if self.tensor is not None else None   # computed on first use
        self._tree = None
        self._cn = None

    # -- structured ---------------------------------------------------------------------------------------
    def cell_nodes(self) -> np.ndarray:
        """Tensor meshes: ``(n_x - 1, n_y - 1, 4)`` nodes of every cell (i, j) in skfem reference order (x0,y0),
        (x1,y0), (x1,y1), (x0,y1), so that the shape functions are :func:`_phi` of (X, Y) = ((x - x0)/hx,
        (y - y0)/hy) whatever the mesh's own local node order (init_tensor, for one, numbers its quads
        clockwise)."""
        if self._cn is None:
            xs, ys, _ = self.tensor
            G = tensor_node_grid(self.mesh, xs, ys)
            self._G = G
            self._cn = np.stack([G[:-1, :-1], G[1:, :-1], G[1:, 1:], G[:-1, 1:]], axis=-1)
        return self._cn

    @property
    def node_grid(self) -> np.ndarray:
        """Tensor meshes: ``(n_x, n_y)`` index of the node at every grid position (axial i, lateral j)."""
        self.cell_nodes()
        return self._G

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
        return Location(inside, cell[i, j], self.cell_nodes()[i, j], N, dphi)

    def locate_grid(self, xa, ya) -> Location:
        """Locate the tensor grid of points (xa[i], ya[j]) (C order).  Separable and fast on tensor meshes: the
        result carries ``grid`` and builds its per-point arrays only when they are used."""
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
        cn = self.cell_nodes()

        def AX():                                               # (nr, 4) axial factors of the 4 shape functions
            return np.stack([1 - X, X, X, 1 - X], axis=1)

        def AY():                                               # (nc, 4) lateral factors
            return np.stack([1 - Y, 1 - Y, Y, Y], axis=1)

        def dN():
            dAX = np.array([-1.0, 1.0, 1.0, -1.0])[None, :] / hx[:, None]
            dAY = np.array([-1.0, -1.0, 1.0, 1.0])[None, :] / hy[:, None]
            ax, ay = AX(), AY()
            out = np.empty((i.size * j.size, 4, 2))
            out[:, :, 0] = (dAX[:, None, :] * ay[None, :, :]).reshape(-1, 4)
            out[:, :, 1] = (ax[:, None, :] * dAY[None, :, :]).reshape(-1, 4)
            return out

        # each per-point array is built on first use, on its own (e.g. the element index alone is cheap)
        fill = {"_element": lambda: cell[i[:, None], j[None, :]].ravel(),
                "_nodes": lambda: cn[i[:, None], j[None, :]].reshape(-1, 4),
                "_N": lambda: (AX()[:, None, :] * AY()[None, :, :]).reshape(-1, 4),
                "_dN": dN}
        # separable description (rows x cols of inside points), used for fast pixel-quadrature assembly
        grid = GridLocation((AxisLocation(i, X, hx, np.flatnonzero(inx)), AxisLocation(j, Y, hy, np.flatnonzero(iny))))
        return Location(inside, grid=grid, fill=fill)

    # -- logically structured (moved tensor mesh) -------------------------------------------------------
    def _walk(self, pts, steps: int = 8):
        """Newton walk on a logically structured mesh; returns (elem, X, Y, nodes) with elem = -1 where the walk
        did not settle (those points go to the general search)."""
        G, cell, cn = self._logical
        p = self.mesh.p
        rows = p[0][G].mean(axis=1)                  # mean axial position of each grid row, (nx,)
        cols = p[1][G].mean(axis=0)
        nxe, nye = cell.shape
        # the mean rows/columns are increasing for an unfolded mesh moved by a smooth field; if not, no guess
        if np.any(np.diff(rows) <= 0) or np.any(np.diff(cols) <= 0):
            n = len(pts)
            return np.full(n, -1), np.zeros(n), np.zeros(n), np.zeros((n, 4), np.int64)
        n = len(pts)
        elem = np.full(n, -1, dtype=np.int64)
        X = np.zeros(n)
        Y = np.zeros(n)
        nodes = np.zeros((n, 4), dtype=np.int64)
        tol = 1e-9
        size = float(np.ptp(p, axis=1).max())
        if _kernels.use_compiled():
            _kernels.walk_kernel(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                         np.ascontiguousarray(p[0]), np.ascontiguousarray(p[1]), cn, cell, rows, cols, steps, tol,
                         1e-9 * size, elem, X, Y, nodes)
            return elem, X, Y, nodes
        a = np.clip(np.searchsorted(rows, pts[:, 0]) - 1, 0, nxe - 1)
        b = np.clip(np.searchsorted(cols, pts[:, 1]) - 1, 0, nye - 1)
        todo = np.arange(n)
        for _ in range(steps):
            if todo.size == 0:
                break
            nd = cn[a, b]                                   # (k, 4)
            Xc, Yc, res = _invert_bilinear(pts[todo], p[0][nd].T, p[1][nd].T)
            ok = ((Xc >= -tol) & (Xc <= 1 + tol) & (Yc >= -tol) & (Yc <= 1 + tol) & np.isfinite(Xc + Yc)
                  & (res <= 1e-9 * size))
            hit = todo[ok]
            elem[hit] = cell[a[ok], b[ok]]
            X[hit] = np.clip(Xc[ok], 0, 1)
            Y[hit] = np.clip(Yc[ok], 0, 1)
            nodes[hit] = nd[ok]
            # step towards the cell the reference coordinates point to; stuck at the grid's edge -> give up
            da = np.where(Xc > 1 + tol, 1, np.where(Xc < -tol, -1, 0))
            db = np.where(Yc > 1 + tol, 1, np.where(Yc < -tol, -1, 0))
            na, nb = np.clip(a + da, 0, nxe - 1), np.clip(b + db, 0, nye - 1)
            moving = ~ok & ((na != a) | (nb != b)) & np.isfinite(Xc + Yc)
            todo, a, b = todo[moving], na[moving], nb[moving]
        return elem, X, Y, nodes

    # -- general ------------------------------------------------------------------------------------------
    def _newton(self, pts, e, iters: int = 12):
        """Invert the bilinear map of elements e at pts; returns X, Y (reference) and the residual (mm)."""
        t = self.mesh.t[:, e]
        return _invert_bilinear(pts, self.mesh.p[0][t], self.mesh.p[1][t], iters)

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
        # nearest centroid first (resolves almost every point), then all k nearest for the rest (from the first
        # again: with two centroids at the same distance the k = 1 and k = 8 queries may rank them differently)
        for kk in sorted({1, k}):
            if todo.size == 0:
                break
            _, cand = self._tree.query(pts[todo], k=kk)
            cand = np.asarray(cand).reshape(todo.size, kk)
            for c in range(kk):
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
        if self._logical is None:
            self._logical = logical_grid(self.mesh) or False
        n = len(pts)
        if self._logical:
            elem, X, Y, nodes = self._walk(pts)
            rest = np.flatnonzero(elem < 0)
        else:
            elem, X, Y, nodes = np.full(n, -1, dtype=np.int64), np.zeros(n), np.zeros(n), None
            rest = np.arange(n)
        if rest.size:
            ins, e, Xr, Yr = self._locate_general(pts[rest])
            found = rest[ins]
            elem[found], X[found], Y[found] = e, Xr, Yr
            if nodes is not None:
                nodes[found] = self.mesh.t[:, e].T
        inside = elem >= 0
        e, X, Y = elem[inside], X[inside], Y[inside]
        nodes = self.mesh.t[:, e].T if nodes is None else nodes[inside]
        nodes = np.ascontiguousarray(nodes, dtype=np.int64)
        N = np.empty((e.size, 4))
        N[:, 0] = (1 - X) * (1 - Y)
        N[:, 1] = X * (1 - Y)
        N[:, 2] = X * Y
        N[:, 3] = (1 - X) * Y
        mesh = self.mesh
        # physical gradients only when used (strain sampling; the image term needs N alone)
        return Location(inside, e, nodes, N, fill={"_dN": lambda: _physical_gradients(mesh, nodes, _phi(X, Y)[1])})


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
    axes : ((nr,), (nc,)) float, mm, or None
        When the pixels are a block (``block``): its row and column centres, ``points`` their outer product.
    weights : (m,) float, mm^2
        Midpoint-rule weights, dx * dy each.
    P : (m, n_nodes) csr
        Pixel->node interpolation operator.
    location : Location
    """

    #: The midpoint rule's weights are all dx * dy.
    weights_constant = True

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
        xa = self.origin[0] + np.arange(i0, i1 + 1) * self.spacing[0]
        ya = self.origin[1] + np.arange(j0, j1 + 1) * self.spacing[1]
        loc = self.locator.locate_grid(xa, ya)
        self.location = loc
        #: (row slice, column slice) of the image holding the quadrature pixels in C order, when they are a
        #: block (tensor meshes), else None: the image term then slices instead of gathering
        self.block = None
        if loc.grid is not None:
            rows, cols = loc.grid.rows, loc.grid.cols
            nr, nc = rows.size, cols.size
            self.index = ((i0 + rows)[:, None] * self.shape[1] + (j0 + cols)[None, :]).ravel()
            self.axes = (xa[rows], ya[cols])
            self._points = None             # built on first use from the axes
            if nr and nc:
                self.block = (slice(i0 + rows[0], i0 + rows[0] + nr), slice(j0 + cols[0], j0 + cols[0] + nc))
        else:
            ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
            ii, jj = ii.ravel(), jj.ravel()
            ins = loc.inside
            self.index = (ii * self.shape[1] + jj)[ins]
            self.axes = None
            self._points = np.column_stack([xa[ii[ins] - i0], ya[jj[ins] - j0]])
        self.weights = np.full(self.index.size, self.spacing[0] * self.spacing[1])
        self.n_nodes = mesh.p.shape[1]
        self._P = None
        self._PT = None

    @property
    def points(self) -> np.ndarray:
        """Centres of the quadrature pixels (m, 2) mm (on a block: built on first use from ``axes``)."""
        if self._points is None:
            xr, yc = self.axes
            pts = np.empty((xr.size * yc.size, 2))
            pts[:, 0] = np.repeat(xr, yc.size)
            pts[:, 1] = np.tile(yc, xr.size)
            self._points = pts
        return self._points

    @property
    def P(self) -> sp.csr_matrix:
        """Pixel->node interpolation operator (m, n_nodes), built on first use."""
        if self._P is None:
            self._P = self.location.operator(self.n_nodes)
        return self._P

    @property
    def PT(self) -> sp.csr_matrix:
        """``P.T`` in CSR (node <- pixel sums), built on first use."""
        if self._PT is None:
            self._PT = self.P.T.tocsr()
        return self._PT

    @property
    def n_pixels(self) -> int:
        return int(self.index.size)


def pixel_values(quad, v) -> np.ndarray:
    """Nodal scalar ``v`` (n_nodes,) at the quadrature pixels of ``quad`` (:class:`femreg.pixels.PixelQuadrature`),
    (n_pixels,).  On a tensor mesh by two 1D interpolations of the node grid (rows, then columns), without the
    per-pixel shape-function arrays."""
    loc = quad.location
    gr = loc.grid
    if gr is None:
        return quad.P @ v
    Vg = np.asarray(v, float)[quad.locator.node_grid]                      # (nx, ny)
    i, X, j, Y = gr.i, gr.X, gr.j, gr.Y
    A = (1.0 - X)[:, None] * Vg[i] + X[:, None] * Vg[i + 1]                  # (nr, ny)
    return ((1.0 - Y)[None, :] * A[:, j] + Y[None, :] * A[:, j + 1]).ravel()
