"""Sampling a nodal displacement field on points and on grids: the one home of the paths that
:class:`femreg.RegistrationResult` (``displacement``, ``strain``, ``on_grid``) and the writers use.

A grid of samples is a :class:`PixelGrid` (the reference pixel grid: ``shape``, ``spacing``, ``origin`` mm).  On a
tensor mesh its points are located separably (:meth:`femreg.pixels.PointLocator.locate_grid` ->
:class:`femreg.pixels.GridLocation`) and the fields are interpolated in one compiled pass (:mod:`femreg._kernels`)
or separably in numpy (1D hats along each axis); on any other mesh point by point (:func:`femreg.fields.sample`).
All paths use the same shape functions and elements (equal to round-off); NaN outside the mesh.

Fields: ``ux``, ``uy`` (mm) and the small strains ``exx``, ``eyy``, ``exy`` -- the gradient of the bilinear field
(``strain="element"``) or the recovered nodal strains interpolated like u (``"recovered"``,
:func:`femreg.fields.recovered_strains`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _kernels
from .fields import FIELDS, check_strain_mode, sample
from .image import pixel_axes

__all__ = ["PixelGrid", "sample_points", "sample_grid"]


@dataclass(frozen=True)
class PixelGrid:
    """A grid of samples: ``shape`` (n_axial, n_lateral), ``spacing`` (dx, dy) mm, ``origin`` (2,) mm the centre of
    sample [0, 0]; ``axes()`` the axial and lateral sample coordinates, ``points()`` all of them (C order)."""

    shape: tuple
    spacing: tuple
    origin: tuple

    @classmethod
    def of(cls, shape, spacing, origin) -> "PixelGrid":
        return cls(tuple(int(s) for s in shape), tuple(float(s) for s in np.ravel(spacing)),
                   tuple(float(s) for s in np.ravel(origin)))

    def axes(self):
        return pixel_axes(self.shape, np.asarray(self.spacing), np.asarray(self.origin))

    def points(self) -> np.ndarray:
        """Sample centres (n_axial * n_lateral, 2) mm, C order."""
        x, y = self.axes()
        X, Y = np.meshgrid(x, y, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()])


def sample_points(u, locator, points, names, nodal_strain=None) -> np.ndarray:
    """Fields ``names`` (of ``ux, uy, exx, eyy, exy``) of the nodal vector ``u`` (2 n_nodes,) at ``points`` (n, 2)
    mm -> (n, len(names)), NaN outside the mesh; ``nodal_strain`` (n_nodes, 3) or per-element corners (4, n_el, 3):
    recovered strains (:func:`femreg.fields.sample`), else element
    strains.  ``locator``: the mesh's :class:`femreg.pixels.PointLocator`."""
    pts = np.asarray(points, float).reshape(-1, 2)
    loc = locator.locate(pts)
    f = sample(u, loc, tuple(names), nodal_strain=nodal_strain, mesh_cells=locator.mesh.t)
    out = np.full((len(pts), len(names)), np.nan)
    out[loc.inside] = np.column_stack([f[k] for k in names])
    return out


def sample_grid(u, locator, grid: PixelGrid, strain: str = "element", nodal_strain=None) -> dict:
    """ux, uy, exx, eyy, exy of the nodal vector ``u`` on ``grid``, each ``grid.shape`` float64, NaN outside the
    mesh.  ``strain="recovered"`` needs ``nodal_strain`` (n_nodes, 3) [exx, eyy, exy] or per-element corner values
    (4, n_el, 3) (:func:`femreg.fields.edge_aware_strains`)."""
    loc = locator.locate_grid(*grid.axes())           # separable on tensor meshes
    if check_strain_mode(strain) == "element":
        return _element_fields(u, locator, loc, grid.shape)
    ns = nodal_strain
    if np.ndim(ns) == 3:       # per-element corner values (edge-aware recovery): discontinuous, per point
        f = sample(u, loc, FIELDS, nodal_strain=ns, mesh_cells=locator.mesh.t)
        g = {}
        for k in FIELDS:
            g[k] = np.full(grid.shape[0] * grid.shape[1], np.nan)
            g[k][loc.inside] = f[k]
            g[k] = g[k].reshape(grid.shape)
        return g
    fast = _nodal_fields(np.column_stack([u[0::2], u[1::2], ns]), locator, loc, grid.shape)
    if fast is not None:       # one compiled pass over the samples for all five fields
        return dict(zip(("ux", "uy", "exx", "eyy", "exy"), fast))
    # u, then the recovered nodal strains interpolated like u (two strain components per pass)
    g = _element_fields(u, locator, loc, grid.shape)
    a = _element_fields(ns[:, :2].ravel(), locator, loc, grid.shape)
    b = _element_fields(np.column_stack([ns[:, 2], np.zeros(len(ns))]).ravel(), locator, loc, grid.shape)
    return {"ux": g["ux"], "uy": g["uy"], "exx": a["ux"], "eyy": a["uy"], "exy": b["ux"]}


def _nan_outside(out, rows, cols):
    """NaN in ``out`` (k, n_axial, n_lateral) outside the block of consecutive ``rows`` x ``cols`` (all of it when
    they are empty); the block itself is left for the caller to fill."""
    if not (len(rows) and len(cols)):
        out[...] = np.nan
        return
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    out[:, :r0] = out[:, r1:] = np.nan
    out[:, r0:r1, :c0] = out[:, r0:r1, c1:] = np.nan


def _inside_rows_cols(loc, shape):
    """Grid rows and columns with points inside the mesh (``loc.grid``: they form a block)."""
    ins = loc.inside.reshape(shape)
    return np.flatnonzero(ins.any(axis=1)), np.flatnonzero(ins.any(axis=0))


def _nodal_fields(values, locator, loc, shape):
    """(k, n_axial, n_lateral) bilinear interpolation of nodal ``values`` (n_nodes, k) on the grid, NaN outside the
    mesh; None where no compiled separable pass applies (then :func:`_element_fields`)."""
    if loc.grid is None or not _kernels.use_compiled():
        return None
    rows, cols = _inside_rows_cols(loc, shape)
    k = values.shape[1]
    out = np.empty((k,) + tuple(shape))
    _nan_outside(out, rows, cols)
    if rows.size:
        G, gr = locator.node_grid, loc.grid
        F = np.ascontiguousarray(np.moveaxis(np.asarray(values, float)[G], -1, 0))
        _kernels.grid_values(F, gr.i, gr.X, gr.j, gr.Y, int(rows[0]), int(cols[0]), out)
    return out


def _element_fields(u, locator, loc, shape) -> dict:
    """ux, uy and the element-gradient strains of the nodal vector ``u`` (2 n_nodes,) on the grid located by
    ``loc`` (``locator.locate_grid``)."""
    shape = tuple(shape)
    if loc.grid is not None:     # the inside points are a block of rows x columns
        rows, cols = _inside_rows_cols(loc, shape)
        block = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)) if rows.size else None
        if _kernels.use_compiled() and block is not None:     # one compiled pass, into the grids
            out = np.empty((len(FIELDS),) + shape)
            _nan_outside(out, rows, cols)
            G, gr = locator.node_grid, loc.grid
            _kernels.grid_fields(u[0::2][G], u[1::2][G], gr.i, gr.X, gr.hx, gr.j, gr.Y, gr.hy, int(rows[0]),
                                 int(cols[0]), out)
            return dict(zip(FIELDS, out))
        grid = {}
        for k, v in _separable_fields(u, loc.grid, locator.node_grid).items():
            grid[k] = np.full(shape, np.nan)
            if block is not None:
                grid[k][block] = v.reshape(rows.size, cols.size)
        return grid
    g = {k: np.full(shape[0] * shape[1], np.nan) for k in FIELDS}
    for k, v in sample(u, loc).items():
        g[k][loc.inside] = v
    return {k: v.reshape(shape) for k, v in g.items()}


def _separable_fields(u, gr, G) -> dict:
    """:func:`femreg.fields.sample` on a tensor grid of points in a tensor mesh (``gr``: the
    :class:`femreg.pixels.GridLocation`, ``G`` the node grid), separably: the nodal values on the node grid are
    interpolated along the lateral axis (1D hats, or their derivative), then along the axial one.  The same
    shape functions and elements as ``sample`` (equal to round-off), without its per-pixel (m, 4, 2) gradients."""
    i, j, X, Y, hx, hy = gr.i, gr.j, gr.X, gr.Y, gr.hx, gr.hy
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
