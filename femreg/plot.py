"""Figures: B-mode images, pixel-grid fields (displacement, strain) with colour bars and mm axes, a summary
figure of a registration result, and an off-screen pyvista render of the FE mesh coloured by a field.

Axes: lateral y (mm) horizontal, axial x (mm) vertical and increasing downwards (depth), as on a scanner.
Every ``plot_*`` function takes ``ax=`` (a new figure when None) and returns the Axes.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["bmode", "plot_bmode", "plot_field", "plot_result", "render_mesh", "extent_mm"]


def _mpl():
    import matplotlib

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _image2d(a, name):
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2 or min(arr.shape) < 2:
        raise InputError(f"{name} must be a 2D (axial, lateral) array, got shape {arr.shape}")
    return arr


def bmode(rf, dynamic_range=50.0, *, reference=None):
    """Log-compressed envelope of RF (axial along axis 0) in dB, clipped to ``[-dynamic_range, 0]``.

    Envelope = ``|hilbert(rf, axis=0)|`` (:func:`femreg.speckle.envelope`); 0 dB is its maximum (or ``reference``
    if given, e.g. to put several frames on one scale).  Returns float64 (axial, lateral).
    """
    from .speckle import envelope

    arr = _image2d(rf, "rf")
    if not np.all(np.isfinite(arr)):
        raise InputError("rf contains NaN/Inf")
    if not (np.isfinite(dynamic_range) and dynamic_range > 0):
        raise InputError(f"dynamic_range must be positive (dB), got {dynamic_range!r}")
    env = envelope(arr)
    ref = float(reference) if reference is not None else float(env.max())
    if ref <= 0:
        return np.full(arr.shape, -float(dynamic_range))
    with np.errstate(divide="ignore"):
        db = 20.0 * np.log10(env / ref)
    return np.clip(db, -float(dynamic_range), 0.0)


def extent_mm(shape, spacing, origin=(0.0, 0.0)):
    """imshow extent [left, right, bottom, top] in mm for pixel centres at origin + (i dx, j dy)."""
    dx, dy = (float(s) for s in spacing)
    x0, y0 = (float(o) for o in origin)
    n_ax, n_lat = shape
    return [y0 - dy / 2, y0 + (n_lat - 0.5) * dy, x0 + (n_ax - 0.5) * dx, x0 - dx / 2]


def _ax(ax, figsize=(5, 6)):
    if ax is None:
        plt = _mpl()
        _, ax = plt.subplots(figsize=figsize, constrained_layout=True)
    return ax


def _spacing(spacing):
    from .io.frames import check_spacing

    if spacing is None:
        raise InputError("spacing (dx, dy) in mm is required for mm axes")
    return check_spacing(spacing)


def _draw(ax, img, ext, positions, **kw):
    """imshow of a pixel-grid image, or (``positions`` = physical (X, Y) of every sample of a convex / sector
    frame, :mod:`femreg.geometry`) a scan-converted pcolormesh at the samples' physical positions."""
    if positions is None:
        return ax.imshow(img, extent=ext, interpolation="nearest", **kw)
    X, Y = positions
    aspect = kw.pop("aspect", "equal")
    im = ax.pcolormesh(Y, X, img, shading="nearest", rasterized=True, **kw)
    ax.set_aspect(aspect)
    ax.set_xlim(np.min(Y), np.max(Y))
    ax.set_ylim(np.max(X), min(np.min(X), 0.0))
    return im


def _label(ax, title):
    ax.set_xlabel("lateral y (mm)")
    ax.set_ylabel("axial x (mm)")
    if title:
        ax.set_title(title)


def plot_bmode(rf, spacing, origin=(0.0, 0.0), ax=None, *, dynamic_range=50.0, title="B-mode", colorbar=True,
               aspect="equal", positions=None):
    """B-mode image of ``rf`` (see :func:`bmode`) with mm axes and a dB colour bar; returns the Axes.
    ``positions``: physical (X, Y) of the samples of a convex / sector frame (scan-converted)."""
    sp = _spacing(spacing)
    img = bmode(rf, dynamic_range)
    ax = _ax(ax)
    im = _draw(ax, img, extent_mm(img.shape, sp, origin), positions, cmap="gray", vmin=-dynamic_range, vmax=0,
               aspect=aspect)
    _label(ax, title)
    if colorbar:
        ax.figure.colorbar(im, ax=ax, label="dB")
    return ax


def plot_field(field, spacing, origin=(0.0, 0.0), ax=None, *, title=None, cmap="RdBu_r", vmin=None, vmax=None,
               overlay_bmode=None, alpha=0.7, label=None, dynamic_range=50.0, aspect="equal", symmetric=None,
               positions=None):
    """A pixel-grid field (NaN = outside the mesh, left transparent) with mm axes and a colour bar.

    ``overlay_bmode``: RF of the same shape drawn as a grey B-mode beneath the field, which is then drawn with
    opacity ``alpha``.  Colour limits default to robust percentiles (1, 99) of the finite values, symmetric
    about 0 for diverging maps (``symmetric=None`` decides from ``cmap``).  ``positions``: physical (X, Y) of
    the samples of a convex / sector frame (scan-converted).  Returns the Axes.
    """
    sp = _spacing(spacing)
    f = _image2d(field, "field")
    ax = _ax(ax)
    ext = extent_mm(f.shape, sp, origin)
    if overlay_bmode is not None:
        b = _image2d(overlay_bmode, "overlay_bmode")
        if b.shape != f.shape:
            raise InputError(f"overlay_bmode shape {b.shape} differs from the field's {f.shape}")
        _draw(ax, bmode(b, dynamic_range), ext, positions, cmap="gray", vmin=-dynamic_range, vmax=0,
              aspect=aspect)
    finite = f[np.isfinite(f)]
    if symmetric is None:
        symmetric = cmap in ("RdBu_r", "RdBu", "seismic", "bwr", "coolwarm", "PuOr", "PiYG")
    if finite.size:
        lo, hi = np.percentile(finite, [1, 99])
        if symmetric:
            m = max(abs(lo), abs(hi)) or 1.0
            lo, hi = -m, m
        elif hi <= lo:
            lo, hi = lo - 1.0, hi + 1.0
    else:
        lo, hi = -1.0, 1.0
    vmin = lo if vmin is None else vmin
    vmax = hi if vmax is None else vmax
    masked = np.ma.masked_invalid(f)
    im = _draw(ax, masked, ext, positions, cmap=cmap, vmin=vmin, vmax=vmax, aspect=aspect,
               alpha=alpha if overlay_bmode is not None else None)
    _label(ax, title)
    ax.figure.colorbar(im, ax=ax, label=label or "")
    return ax


_PANELS = (("ux", "axial displacement $u_x$", "mm"), ("uy", "lateral displacement $u_y$", "mm"),
           ("exx", "axial strain $\\varepsilon_{xx}$", ""), ("eyy", "lateral strain $\\varepsilon_{yy}$", ""),
           ("exy", "shear strain $\\varepsilon_{xy}$", ""))


def plot_result(result, out_png=None, *, reference=None, overlay=False, dpi=100, dynamic_range=50.0,
                figsize=None):
    """Summary figure of a registration result: B-mode (if ``reference`` RF, or a ``reference``/``rf`` key in
    the result, is available; the mesh otherwise) and ux, uy, exx, eyy, exy on the pixel grid.

    Parameters
    ----------
    result : path to a result .npz, a dict, or an engine result object (see :mod:`femreg.io.results`).
    out_png : path, optional
        Where to save the figure (PNG).  The figure is returned either way.
    reference : (axial, lateral) RF of the reference image, optional.
    overlay : draw each field over the B-mode.
    """
    from .io.results import as_result_dict, check_mesh

    d = as_result_dict(result)
    for k in ("spacing",) + tuple(p[0] for p in _PANELS):
        if k not in d:
            raise InputError(f"result lacks {k!r}: plot_result needs the pixel-grid fields ux, uy, exx, eyy, exy")
    sp = _spacing(d["spacing"])
    origin = tuple(np.asarray(d.get("origin", (0.0, 0.0)), dtype=float).ravel()[:2])
    shape = np.shape(d["ux"])
    if reference is None:
        reference = d.get("reference", d.get("rf"))
    if reference is not None:
        reference = _image2d(reference, "reference")
        if reference.shape != shape:
            raise InputError(f"reference shape {reference.shape} differs from the result grid {shape}")
    positions = _beam_positions(result, d, shape, sp, origin)
    plt = _mpl()
    n_ax, n_lat = shape
    aspect_ratio = (n_ax * sp[0]) / max(n_lat * sp[1], 1e-12)
    if positions is not None:
        aspect_ratio = float(np.ptp(positions[0]) / max(np.ptp(positions[1]), 1e-12))
    if figsize is None:
        w = 3.4
        figsize = (3 * w, 2 * min(max(w * aspect_ratio, 2.5), 6.0) + 0.6)
    fig, axes = plt.subplots(2, 3, figsize=figsize, constrained_layout=True)
    axes = axes.ravel()
    aspect = "equal" if 0.2 < aspect_ratio < 5 else "auto"  # very tall/flat grids fill the panel
    if reference is not None:
        plot_bmode(reference, sp, origin, ax=axes[0], dynamic_range=dynamic_range, aspect=aspect,
                   positions=positions)
    else:
        p, t, _ = check_mesh(d["mesh_points"], d["mesh_cells"], d["u"])
        ax = axes[0]
        from matplotlib.collections import PolyCollection

        polys = np.stack([p[1][t].T, p[0][t].T], axis=-1)  # (n_el, 4, [y, x])
        ax.add_collection(PolyCollection(polys, facecolor="none", edgecolor="k", linewidth=0.3))
        ext = extent_mm(shape, sp, origin) if positions is None else (
            p[1].min(), p[1].max(), p[0].max(), p[0].min())
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect(aspect)
        _label(ax, f"mesh ({t.shape[1]} quads)")
    for ax, (key, title, unit) in zip(axes[1:], _PANELS):
        cmap = "RdBu_r"
        plot_field(d[key], sp, origin, ax=ax, title=title, cmap=cmap, label=unit,
                   overlay_bmode=reference if overlay else None, aspect=aspect, dynamic_range=dynamic_range,
                   positions=positions)
    info = []
    if "regularizer" in d:
        info.append(f"regulariser {d['regularizer']}")
    if "alpha" in d:
        info.append(f"alpha {float(d['alpha']):.3g}")
    for k in ("ncc_before", "ncc_after"):
        if k in d:
            info.append(f"{k} {float(d[k]):.3f}")
    if info:
        fig.suptitle(", ".join(info))
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def _beam_positions(result, d, shape, spacing, origin):
    """Physical (X, Y) of the samples when ``result`` is a convex / sector result (its ``sample_positions``, or
    the ``geometry_*`` keys of its file), else None."""
    if hasattr(result, "sample_positions"):
        return result.sample_positions()
    if "geometry_kind" not in d:
        return None
    from .geometry import as_geometry

    geo = as_geometry(dict(kind=str(d["geometry_kind"]), radius_mm=float(d["geometry_radius_mm"]),
                           angle_pitch_deg=float(d["geometry_angle_pitch_deg"])))
    return geo.sample_positions(shape, spacing, origin)


def render_mesh(mesh_points, mesh_cells, values=None, out_png=None, *, name="value", cmap="viridis",
                window_size=(800, 600), show_edges=True, clim=None):
    """Off-screen pyvista render of the quad mesh coloured by ``values``.

    ``values``: (n_nodes,) point data or (n_el,) cell data (None: plain mesh).  Viewed from +z with the
    lateral axis horizontal and depth downwards.  Writes ``out_png`` (window_size pixels) and returns its Path.
    Uses EGL (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``) unless the environment chose otherwise.
    """
    from .io.results import check_mesh

    p, t, _ = check_mesh(mesh_points, mesh_cells)
    if out_png is None:
        raise InputError("render_mesh needs out_png")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    pv.OFF_SCREEN = True
    pts = np.zeros((p.shape[1], 3))
    pts[:, 0] = p[1]  # lateral -> screen x
    pts[:, 1] = -p[0]  # depth down
    cells = np.hstack([np.full((t.shape[1], 1), 4), t.T]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(t.shape[1], pv.CellType.QUAD, dtype=np.uint8), pts)
    kw = {}
    if values is not None:
        v = np.asarray(values, dtype=float).ravel()
        if v.size == p.shape[1]:
            grid.point_data[name] = v
        elif v.size == t.shape[1]:
            grid.cell_data[name] = v
        else:
            raise InputError(f"values has {v.size} entries; need n_nodes = {p.shape[1]} or n_el = {t.shape[1]}")
        kw = dict(scalars=name, cmap=cmap, clim=clim, scalar_bar_args={"title": name, "vertical": True, "position_x": 0.85,
                                                                 "position_y": 0.1, "height": 0.8})
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        plotter.add_mesh(grid, show_edges=show_edges, **kw)
        plotter.view_xy()
        plotter.camera.zoom(1.15)
        plotter.screenshot(str(out_png))
    finally:
        plotter.close()
    return Path(out_png)


# ----------------------------------------------------------------------------------------------------------------
# shear-modulus images (femreg.invert)
# ----------------------------------------------------------------------------------------------------------------
def plot_mesh_values(mesh_points, mesh_cells, values, ax=None, *, title=None, cmap="viridis", log=False,
                     vmin=None, vmax=None, label=None):
    """Element values (n_el,) on a quad mesh (``mesh_points`` (2, n_nodes) [x, y] mm, ``mesh_cells`` (4, n_el)),
    lateral horizontal and depth downwards, with a colour bar; ``log=True`` uses a logarithmic colour scale.
    Returns the Axes."""
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import LogNorm, Normalize

    p = np.asarray(mesh_points, float)
    t = np.asarray(mesh_cells, np.int64)
    v = np.asarray(values, float).ravel()
    if v.size != t.shape[1]:
        raise InputError(f"values has {v.size} entries, the mesh {t.shape[1]} elements")
    ax = _ax(ax)
    finite = v[np.isfinite(v)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.1, 1.0))
    if log:
        lo, hi = (max(lo, 1e-12), max(hi, 1e-12))
    lo = lo if vmin is None else vmin
    hi = hi if vmax is None else vmax
    if hi <= lo:
        lo, hi = (lo / 1.1, hi * 1.1) if log else (lo - 1.0, hi + 1.0)
    norm = LogNorm(lo, hi) if log else Normalize(lo, hi)
    polys = np.stack([p[1][t].T, p[0][t].T], axis=-1)      # (n_el, 4, [y, x])
    pc = PolyCollection(polys, array=np.ma.masked_invalid(v), cmap=cmap, norm=norm, edgecolors="face",
                        linewidths=0.2)
    ax.add_collection(pc)
    ax.set_xlim(p[1].min(), p[1].max())
    ax.set_ylim(p[0].max(), p[0].min())
    ax.set_aspect("equal")
    _label(ax, title)
    ax.figure.colorbar(pc, ax=ax, label=label or "")
    return ax


def plot_inversion(result, out_png=None, *, dpi=100, figsize=None, title=None):
    """The relative shear-modulus image of :func:`femreg.invert` beside the measured axial strain, on the
    inversion mesh.  ``result``: an :class:`femreg.inversion.InversionResult` (a file: read it with
    :func:`femreg.load_inversion`; ``InversionResult.plot`` is this function).  Writes ``out_png`` if given;
    returns the figure."""
    if not all(hasattr(result, k) for k in ("mesh", "mu", "strain_measured", "model", "beta")):
        raise InputError(f"plot_inversion needs an InversionResult (femreg.load_inversion reads a file), got "
                         f"{type(result).__name__}")
    res = result
    plt = _mpl()
    p = res.mesh.p
    ext = (p[0].max() - p[0].min()) / max(p[1].max() - p[1].min(), 1e-12)
    if figsize is None:
        figsize = (9.0, min(max(3.6 * ext, 2.5), 8.0) + 0.8)
    fig, axes = plt.subplots(1, 2, figsize=figsize, constrained_layout=True)
    plot_mesh_values(p, res.mesh.t, res.mu, ax=axes[0], log=True, cmap="viridis",
                     title="shear modulus $\\mu$ (relative, median 1)", label="$\\mu / \\mathrm{median}$")
    exx = res.strain_measured[:, 0]
    m = float(np.nanpercentile(np.abs(exx), 99)) if np.isfinite(exx).any() else 1.0
    plot_mesh_values(p, res.mesh.t, exx, ax=axes[1], cmap="RdBu_r", title="measured axial strain "
                     "$\\varepsilon_{xx}$", vmin=-m or -1.0, vmax=m or 1.0)
    fig.suptitle(title or f"{res.model}, beta {res.beta:.3g}, {res.regularization.upper()}"
                 + ("" if res.success else f" -- NOT CONVERGED: {res.message}"))
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def plot_quality(mesh_points, mesh_cells, quality, out_png=None, *, ax=None, threshold=0.5, dpi=100):
    """Per-element quality map of a registration (NCC of reference and warped moving image over each element,
    :attr:`femreg.RegistrationResult.quality`) drawn on the mesh, mm axes; elements below ``threshold`` are
    outlined in black.  Returns the Figure (saved to ``out_png`` when given)."""
    from matplotlib.collections import PolyCollection

    p = np.asarray(mesh_points, float)
    t = np.asarray(mesh_cells, np.int64)
    q = np.asarray(quality, float).ravel()
    if p.ndim != 2 or p.shape[0] != 2 or t.ndim != 2 or t.shape[0] != 4 or q.size != t.shape[1]:
        raise InputError(f"quality map needs (2, n) points, (4, n_el) quads and n_el values; got {p.shape}, "
                         f"{t.shape}, {q.size}")
    qmin = np.nanmin(q) if np.isfinite(q).any() else float("nan")
    ax = plot_mesh_values(p, t, q, ax=ax, title=f"registration quality (min {qmin:.2f})", vmin=0.0, vmax=1.0,
                          label="element NCC")
    bad = np.isfinite(q) & (q < threshold)
    if bad.any():
        polys = np.stack([p[1, t].T, p[0, t].T], axis=-1)          # (n_el, 4, [lateral, axial])
        ax.add_collection(PolyCollection(polys[bad], facecolors="none", edgecolors="k", linewidths=1.0))
    if out_png is not None:
        ax.figure.savefig(out_png, dpi=dpi)
    return ax.figure
