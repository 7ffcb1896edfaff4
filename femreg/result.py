"""The result of a registration: :class:`RegistrationResult` (a nodal displacement on a quad mesh, sampled on
points and on the reference pixel grid through :mod:`femreg.sampling`, saved and loaded through the ``.npz``
contract of :mod:`femreg.io.results`), and the conversions of a displacement given as a callable, a nodal vector,
a result or a block-matching field (:func:`displacement_at`, :func:`nodal_values`).
"""
from __future__ import annotations

import numpy as np

from . import _kernels
from .blockmatch import BlockMatchResult
from .errors import InputError
from .fields import FIELDS, check_strain_mode, recovered_strains, sample
from .image import pixel_axes
from .io.results import read_result, save_result
from .pixels import PointLocator

__all__ = ["RegistrationResult", "load_result", "displacement_at", "nodal_values"]


def _nan_outside(out, rows, cols):
    """NaN in ``out`` (k, n_axial, n_lateral) outside the block of consecutive ``rows`` x ``cols`` (all of it when
    they are empty); the block itself is left for the caller to fill."""
    if not (len(rows) and len(cols)):
        out[...] = np.nan
        return
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    out[:, :r0] = out[:, r1:] = np.nan
    out[:, r0:r1, :c0] = out[:, r0:r1, c1:] = np.nan


class RegistrationResult:
    """A registered displacement field on a quad mesh.

    Attributes
    ----------
    mesh : skfem.MeshQuad1
        mm; ``mesh.p[0]`` axial x, ``mesh.p[1]`` lateral y.
    u : (2 n_nodes,) float, mm
        Nodal displacement, interleaved (u[0::2] = ux, u[1::2] = uy), scikit-fem DOF order.
    success, status, message, nit, energy_history
        From the Gauss-Newton solver (:class:`femreg.solver.GaussNewtonResult`).
    regularizer : str
        Name of the regulariser; ``alpha`` its weight (for the RMS-normalised images).
    ncc_before, ncc_after : float
        NCC of reference vs moving over the mesh pixels, at u = 0 and at the result: a quality measure.
    shape, spacing, origin
        Reference pixel grid.
    timings : dict
        Seconds per stage.
    blockmatch : BlockMatchResult or None
        The initial-guess field, if block matching was used.
    quality : (n_elements,) float or None
        Per-element NCC of reference and warped moving image at the result (NaN where an element holds fewer
        than 4 pixels): low values mark decorrelation, peak hopping or a failed region.
    strategy : str
        "auto" or "paper" (see :func:`register`); ``alpha_effective`` the weight used on this mesh
        (:mod:`femreg.scaling`).
    hop_gain : (n_elements,) float or None
        Peak-hopping map of :func:`register`'s check (:func:`femreg.repair.hop_gain`, not saved): per element, how
        much better the envelope matches one RF period off than at u (Fisher z); above
        :data:`femreg.repair.HOP_GAIN` the element sits on a neighbouring correlation peak.
    """

    def __init__(self, mesh, u, *, shape, spacing, origin, regularizer="", alpha=float("nan"), success=False,
                 status=-1, message="", nit=0, energy_history=(), ncc_before=float("nan"),
                 ncc_after=float("nan"), timings=None, blockmatch=None, solver_result=None, grid=None,
                 locator=None, quality=None, strategy="", alpha_effective=float("nan"), hop_gain=None):
        self.mesh = mesh
        self.u = np.asarray(u, float)
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.regularizer = str(regularizer)
        self.alpha = float(alpha)
        self.success = bool(success)
        self.status = int(status)
        self.message = str(message)
        self.nit = int(nit)
        self.energy_history = np.asarray(energy_history, float)
        self.ncc_before = float(ncc_before)
        self.ncc_after = float(ncc_after)
        self.timings = dict(timings or {})
        self.blockmatch = blockmatch
        self.solver_result = solver_result
        self._locator = locator
        self._grid = grid
        self._grid_element = None
        self._nodal_strain = None
        self.quality = None if quality is None else np.asarray(quality, float)
        self.hop_gain = None if hop_gain is None else np.asarray(hop_gain, float)
        self.strategy = str(strategy)
        self.alpha_effective = float(alpha_effective)

    # -- sampling -------------------------------------------------------------------------------------------
    @property
    def locator(self) -> PointLocator:
        if self._locator is None:
            self._locator = PointLocator(self.mesh)
        return self._locator

    @property
    def ux(self):
        return self.u[0::2]

    @property
    def uy(self):
        return self.u[1::2]

    def displacement(self, points) -> np.ndarray:
        """u at ``points`` (n, 2) [x, y] mm -> (n, 2) [ux, uy] mm; NaN outside the mesh."""
        pts = np.asarray(points, float).reshape(-1, 2)
        loc = self.locator.locate(pts)
        f = sample(self.u, loc, ("ux", "uy"))
        out = np.full((len(pts), 2), np.nan)
        out[loc.inside] = np.column_stack([f["ux"], f["uy"]])
        return out

    @property
    def nodal_strain(self) -> np.ndarray:
        """Recovered nodal strains (n_nodes, 3) [exx, eyy, exy] (:func:`femreg.fields.recovered_strains`)."""
        if self._nodal_strain is None:
            self._nodal_strain = recovered_strains(self.mesh.p, self.mesh.t, self.u)
        return self._nodal_strain

    def strain(self, points, strain: str = "recovered") -> np.ndarray:
        """Small strain at ``points`` (n, 2) mm -> (n, 3) [exx, eyy, exy], exy = (dux/dy + duy/dx) / 2;
        NaN outside the mesh.  ``strain="recovered"`` (default): continuous, the nodal average of the
        element-centre strains interpolated bilinearly (:mod:`femreg.fields`); ``"element"``: the gradient of
        the bilinear field, discontinuous across element edges (a point on an edge takes one of its elements)."""
        check_strain_mode(strain)
        pts = np.asarray(points, float).reshape(-1, 2)
        loc = self.locator.locate(pts)
        f = sample(self.u, loc, ("exx", "eyy", "exy"),
                   nodal_strain=self.nodal_strain if strain == "recovered" else None)
        out = np.full((len(pts), 3), np.nan)
        out[loc.inside] = np.column_stack([f["exx"], f["eyy"], f["exy"]])
        return out

    def pixel_points(self) -> np.ndarray:
        """Centres of the reference pixels, (n_axial * n_lateral, 2) mm, C order."""
        x, y = pixel_axes(self.shape, self.spacing, self.origin)
        X, Y = np.meshgrid(x, y, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()])

    def on_grid(self, strain: str = "recovered") -> dict:
        """ux, uy, exx, eyy, exy on the reference pixel grid, each (n_axial, n_lateral) float64, NaN outside
        the mesh; strains as :meth:`strain` (``"recovered"`` or ``"element"``)."""
        if check_strain_mode(strain) == "element":
            if self._grid_element is None:
                self._grid_element = self._interpolate_grid(self.u, self._grid_location())
            return self._grid_element
        if self._grid is None:
            loc = self._grid_location()
            ns = self.nodal_strain
            fast = self._interpolate_nodal_fields(np.column_stack([self.u[0::2], self.u[1::2], ns]), loc)
            if fast is not None:       # one compiled pass over the pixels for all five fields
                self._grid = dict(zip(("ux", "uy", "exx", "eyy", "exy"), fast))
                return self._grid
            # u, then the recovered nodal strains interpolated like u (two strain components per pass)
            g = self._interpolate_grid(self.u, loc)
            a = self._interpolate_grid(ns[:, :2].ravel(), loc)
            b = self._interpolate_grid(np.column_stack([ns[:, 2], np.zeros(len(ns))]).ravel(), loc)
            self._grid = {"ux": g["ux"], "uy": g["uy"], "exx": a["ux"], "eyy": a["uy"], "exy": b["ux"]}
        return self._grid

    def _grid_location(self):
        x, y = pixel_axes(self.shape, self.spacing, self.origin)
        return self.locator.locate_grid(x, y)          # separable on tensor meshes

    def _inside_rows_cols(self, loc):
        """Pixel rows and columns with points inside the mesh (``loc.grid``: they form a block)."""
        ins = loc.inside.reshape(self.shape)
        return np.flatnonzero(ins.any(axis=1)), np.flatnonzero(ins.any(axis=0))

    def _interpolate_nodal_fields(self, values, loc):
        """(k, n_axial, n_lateral) bilinear interpolation of nodal ``values`` (n_nodes, k) on the pixel grid, NaN
        outside the mesh; None where no compiled separable pass applies (then :meth:`_interpolate_grid`)."""
        if loc.grid is None or not _kernels.use_compiled():
            return None
        rows, cols = self._inside_rows_cols(loc)
        k = values.shape[1]
        out = np.empty((k,) + self.shape)
        _nan_outside(out, rows, cols)
        if rows.size:
            G, gr = self.locator.node_grid, loc.grid
            F = np.ascontiguousarray(np.moveaxis(np.asarray(values, float)[G], -1, 0))
            _kernels.grid_values(F, gr["i"], gr["X"], gr["j"], gr["Y"], int(rows[0]), int(cols[0]), out)
        return out

    def _interpolate_grid(self, u, loc) -> dict:
        """ux, uy and the element-gradient strains of the nodal vector ``u`` (2 n_nodes,) on the pixel grid
        (``loc``: :meth:`_grid_location`)."""
        if loc.grid is not None:     # the inside points are a block of rows x columns
            rows, cols = self._inside_rows_cols(loc)
            block = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)) if rows.size else None
            if _kernels.use_compiled() and block is not None:     # one compiled pass, into the grids
                out = np.empty((len(FIELDS),) + self.shape)
                _nan_outside(out, rows, cols)
                xs, ys, _ = self.locator.tensor
                G, gr = self.locator.node_grid, loc.grid
                i, j = gr["i"], gr["j"]
                _kernels.grid_fields(u[0::2][G], u[1::2][G], i, gr["X"], xs[i + 1] - xs[i], j, gr["Y"],
                                     ys[j + 1] - ys[j], int(rows[0]), int(cols[0]), out)
                return dict(zip(FIELDS, out))
            grid = {}
            for k, v in _sample_grid(u, loc, self.locator).items():
                grid[k] = np.full(self.shape, np.nan)
                if block is not None:
                    grid[k][block] = v.reshape(rows.size, cols.size)
            return grid
        g = {k: np.full(self.shape[0] * self.shape[1], np.nan) for k in FIELDS}
        for k, v in sample(u, loc).items():
            g[k][loc.inside] = v
        return {k: v.reshape(self.shape) for k, v in g.items()}

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path, **extra):
        """Write the result as .npz, atomically: the contract of :mod:`femreg.io.results` (mesh, u, grid, pixel-grid
        fields, solver outcome, quality map, strategy), plus any ``extra`` arrays.  Returns the path."""
        return save_result(path, self, **extra)

    def __repr__(self) -> str:
        return (f"RegistrationResult(regularizer={self.regularizer!r}, alpha={self.alpha:g}, "
                f"success={self.success}, nit={self.nit}, n_nodes={self.mesh.p.shape[1]}, "
                f"ncc {self.ncc_before:.3f} -> {self.ncc_after:.3f}, message={self.message!r})")


def _sample_grid(u, loc, locator) -> dict:
    """:func:`femreg.fields.sample` on a tensor grid of points in a tensor mesh (``loc.grid``), separably: the
    nodal values on the node grid are interpolated along the lateral axis (1D hats, or their derivative), then
    along the axial one.  The same shape functions and elements as ``sample`` (equal to round-off); ~10x faster
    on a 0.5 M pixel grid, where the per-pixel (m, 4, 2) gradients dominated."""
    xs, ys, _ = locator.tensor
    G = locator.node_grid
    gr = loc.grid
    i, j, X, Y = gr["i"], gr["j"], gr["X"], gr["Y"]
    hx, hy = xs[i + 1] - xs[i], ys[j + 1] - ys[j]
    u = np.asarray(u, float)
    Ux, Uy = u[0::2][G], u[1::2][G]

    def lateral(U, d=False):       # (n_x nodes, nc): value (or d/dy) at every column
        a, b = U[:, j], U[:, j + 1]
        return (b - a) / hy if d else a + (b - a) * Y

    def axial(V, d=False):         # (nr, nc): value (or d/dx) at every row
        a, b = V[i], V[i + 1]
        return (b - a) / hx[:, None] if d else a + (b - a) * X[:, None]

    Lx, Ly = lateral(Ux), lateral(Uy)
    exy = 0.5 * (axial(lateral(Ux, True)) + axial(Ly, True))
    return {"ux": axial(Lx).ravel(), "uy": axial(Ly).ravel(), "exx": axial(Lx, True).ravel(),
            "eyy": axial(lateral(Uy, True)).ravel(), "exy": exy.ravel()}


def displacement_at(spec, mesh, points, what: str):
    """A displacement given as callable(points)->(n,2), nodal vector (2 n_nodes,), or RegistrationResult."""
    n_nodes = mesh.p.shape[1]
    if isinstance(spec, RegistrationResult):
        v = spec.displacement(points)
        return np.nan_to_num(v, nan=0.0)
    if callable(spec):
        v = np.asarray(spec(np.asarray(points, float)), float)
        if v.shape != (len(points), 2):
            raise InputError(f"{what} callable must return shape ({len(points)}, 2), got {v.shape}")
    else:
        arr = np.asarray(spec, float).ravel()
        if arr.size != 2 * n_nodes:
            raise InputError(f"{what} nodal vector must have 2 * n_nodes = {2 * n_nodes} entries, got {arr.size}")
        loc = PointLocator(mesh).locate(points)
        v = np.zeros((len(points), 2))
        v[loc.inside, 0] = np.sum(loc.N * arr[0::2][loc.nodes], axis=1)
        v[loc.inside, 1] = np.sum(loc.N * arr[1::2][loc.nodes], axis=1)
    if not np.all(np.isfinite(v)):
        raise InputError(f"{what} contains NaN/Inf values")
    return v


def nodal_values(spec, mesh, what="initial"):
    """Nodal interleaved vector (2 n_nodes,) of ``mesh`` from a callable(points) -> (n, 2), a nodal vector, a
    RegistrationResult or a BlockMatchResult (``what`` names it in error messages)."""
    pts = mesh.p.T
    if isinstance(spec, BlockMatchResult):
        v = spec(pts)
    elif not callable(spec) and not isinstance(spec, RegistrationResult):
        arr = np.asarray(spec, float).ravel()
        if arr.size != 2 * mesh.p.shape[1]:
            raise InputError(f"{what} nodal vector must have 2 * n_nodes = {2 * mesh.p.shape[1]} entries, "
                             f"got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{what} contains NaN/Inf values")
        return arr.copy()
    else:
        v = displacement_at(spec, mesh, pts, what)
    u = np.empty(2 * len(pts))
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return u


def load_result(path) -> RegistrationResult:
    """Read a result ``.npz`` (the contract of :mod:`femreg.io.results`) as a :class:`RegistrationResult`.

    The one reader of the contract (``femreg.load_result`` and ``femreg.io.load_result`` are this function).
    Raises :class:`~femreg.errors.FileFormatError` naming the missing key or bad shape when the file is not a
    result."""
    mesh, u, kw, element_grid = read_result(path)
    res = RegistrationResult(mesh, u, **kw)
    res._grid_element = element_grid
    return res
