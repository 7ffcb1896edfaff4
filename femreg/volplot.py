"""Pictures of volumes: three orthogonal slices of B-mode, displacement, strain, modulus and quality with mm axes,
and an off-screen pyvista rendering (orthogonal slices or an iso-surface) written to png.

Volumes are arrays ``(axial, lateral, elevational)`` = ``(x, y, z)``; voxel ``[i, j, k]`` has its centre at
``origin + (i dx, j dy, k dz)`` mm.  Fields come as a dict of such arrays keyed ``ux, uy, uz`` (mm), ``exx, eyy,
ezz, exy, exz, eyz`` (small strain, tensor shear; drawn in %), ``quality`` (NCC, 0-1) and ``modulus`` (any
unit; log scale), as a 3D registration result's ``on_grid`` returns them.  NaN (outside the registered domain)
is drawn as background.

The three slices (:func:`plot_volume_slices`): axial-lateral at elevation ``z`` (the scanner's B-mode plane),
axial-elevational at lateral ``y`` (depth down in both), lateral-elevational at depth ``x`` (a C-plane); dashed
lines in each mark where the other two cut it, the titles say where the slice lies.  Each quantity is a column
with one colour bar under its three slices, which share its limits (:func:`femreg.plot.colour_scale`
conventions: diverging about 0 only for data that changes sign).  Every panel is drawn at its mm aspect, all at
one scale, as large as :data:`PAGE_INCHES` allows: one row per orientation for a shallow, wide volume, a 2 x 2
block per quantity (the two axial slices side by side) for a deep, narrow one; an axis shorter than
1 / :data:`MAX_ASPECT` of the longest is stretched, which its label says.

A 3D modulus inversion (:func:`femreg.invert` on a volume's result) is drawn the same way by
:func:`plot_inversion_volume` (``InversionResult.plot``, ``femreg plot MU.npz --slice``): the relative modulus
and its uncertainty one value per element, and the recovered axial strain, through a point, the centre or the
stiffest / softest region.
"""
from __future__ import annotations

import os
import textwrap
from pathlib import Path

import numpy as np

from .errors import InputError
from .plot import DIVERGING_CMAP, _log_ticks, _mpl, colour_scale, fit_colorbars

__all__ = ["plot_volume_slices", "plot_inversion_volume", "render_volume", "volume_bmode", "FIELD_LABELS",
           "STRAIN_KEYS", "SLICE_CHOICES", "PLANES", "PAGE_INCHES", "MAX_ASPECT"]

STRAIN_KEYS = ("exx", "eyy", "ezz", "exy", "exz", "eyz")
#: Colour-bar label (quantity and unit) of every field key drawn.
FIELD_LABELS = {
    "ux": "axial displacement u_x (mm)", "uy": "lateral displacement u_y (mm)",
    "uz": "elevational displacement u_z (mm)",
    "exx": "axial strain e_xx (%)", "eyy": "lateral strain e_yy (%)", "ezz": "elevational strain e_zz (%)",
    "exy": "shear strain e_xy (%)", "exz": "shear strain e_xz (%)", "eyz": "shear strain e_yz (%)",
    "quality": "quality (local NCC)", "modulus": "modulus (relative)",
}
_ORDER = ("ux", "uy", "uz") + STRAIN_KEYS + ("modulus", "quality")


def _vec3(value, name, positive=False):
    try:
        v = tuple(float(s) for s in value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be three numbers (x, y, z) mm, got {value!r}") from None
    if len(v) != 3 or not all(np.isfinite(v)) or (positive and min(v) <= 0):
        raise InputError(f"{name} must be three {'positive ' if positive else ''}finite numbers (x, y, z) mm, "
                         f"got {value!r}")
    return v


def _volume(a, name):
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 3 or min(arr.shape) < 2:
        raise InputError(f"{name} must be a 3D (axial, lateral, elevational) array, got shape {arr.shape}")
    return arr


def volume_bmode(rf, dynamic_range: float = 50.0) -> np.ndarray:
    """Log-compressed envelope (dB, ``[-dynamic_range, 0]``, 0 at the maximum) of an RF volume, the envelope
    taken along the axial axis of every line (:func:`femreg.speckle.envelope`)."""
    from .speckle import envelope

    arr = _volume(rf, "reference")
    if not np.all(np.isfinite(arr)):
        raise InputError("reference volume contains NaN/Inf")
    env = envelope(arr.reshape(arr.shape[0], -1)).reshape(arr.shape)
    ref = float(env.max())
    if ref <= 0:
        return np.full(arr.shape, -float(dynamic_range))
    with np.errstate(divide="ignore"):
        return np.clip(20.0 * np.log10(env / ref), -float(dynamic_range), 0.0)


def _index(coord, origin, spacing, n, name):
    k = int(round((float(coord) - origin) / spacing))
    if not 0 <= k < n:
        raise InputError(f"slice position {name} = {coord:g} mm lies outside the volume "
                         f"[{origin:g}, {origin + (n - 1) * spacing:g}] mm")
    return k


def _check_fields(fields, keys):
    fields = dict(fields or {})
    if keys is None:
        keys = [k for k in _ORDER if k in fields] + [k for k in fields if k not in _ORDER]
    keys = list(keys)
    missing = [k for k in keys if k not in fields]
    if missing:
        raise InputError(f"fields has no {', '.join(missing)} (keys: {', '.join(fields) or 'none'})")
    arrs = {k: _volume(fields[k], k) for k in keys}
    shapes = {a.shape for a in arrs.values()}
    if len(shapes) > 1:
        raise InputError(f"field arrays differ in shape: {sorted(shapes)}")
    return keys, arrs


def _scale(values):
    """:func:`femreg.plot.colour_scale`, with a range below 1e-9 of the values' size (round-off on a uniform
    field: a recovered strain of -1 % +- 1e-15) taken as constant, padded 5 %: not a scale whose ticks read
    -1.0000000000000."""
    cmap, lo, hi = colour_scale(values)
    if hi - lo <= 1e-9 * max(abs(lo), abs(hi)):
        mid = 0.5 * (lo + hi)
        pad = 0.05 * abs(mid) or 1.0
        cmap, lo, hi = colour_scale(np.array([mid - pad, mid + pad]))
    return cmap, lo, hi


def _style(key, values):
    """(values to draw, cmap, vmin, vmax, norm, label)."""
    label = FIELD_LABELS.get(key, key)
    v = np.asarray(values, float)
    if key in STRAIN_KEYS:
        v = 100.0 * v
    if key == "quality":
        return v, "viridis", 0.0, 1.0, None, label
    if key == "modulus":
        from matplotlib.colors import LogNorm

        pos = v[np.isfinite(v) & (v > 0)]
        if pos.size:
            lo, hi = np.percentile(pos, [1, 99])
            hi = max(hi, lo * 1.01)
            return np.where(v > 0, v, np.nan), "viridis", None, None, LogNorm(lo, hi), label
        return v, "viridis", None, None, None, label
    cmap, lo, hi = _scale(v)
    return v, cmap, lo, hi, None, label


def plot_volume_slices(fields=None, spacing=None, origin=(0.0, 0.0, 0.0), *, reference=None, keys=None, at=None,
                       out_png=None, dynamic_range: float = 50.0, title=None, dpi: int = 100,
                       reference_spacing=None, reference_origin=None, panel_inches: float = 8.0):
    """Three orthogonal slices per quantity: B-mode of ``reference`` (if given) and each field in ``keys``.

    Parameters
    ----------
    fields : dict of (nx, ny, nz) arrays, optional
        Keys of :data:`FIELD_LABELS` (others are drawn with their name as label); strain keys are drawn in %.
    spacing, origin : (dx, dy, dz), (x0, y0, z0) mm
        Grid of the field arrays (and of ``reference`` unless ``reference_spacing`` / ``reference_origin``).
    reference : (nx, ny, nz) RF volume, optional
        Drawn as B-mode (log envelope, ``dynamic_range`` dB).
    keys : list of str, optional
        Which fields, in order (default: all present, displacement, strain, modulus, quality).
    at : (x, y, z) mm, optional
        Where the slices cut (default: the centre of the field grid, or of the reference).
    out_png : path, optional
        Written when given.

    Returns
    -------
    matplotlib.figure.Figure: per quantity the slices axial-lateral (at z), axial-elevational (at y) and
    lateral-elevational (at x) and a colour bar under them; ``fig.volume_axes[(name, plane)]`` is a slice's Axes
    (``name`` "B-mode" or the key, ``plane`` of :data:`PLANES`), ``fig.volume_colorbars[name]`` its colour bar.
    ``panel_inches``: the longest side of a panel at most this (inches).
    """
    keys, arrs = _check_fields(fields, keys)
    if reference is None and not keys:
        raise InputError("nothing to draw: give fields and/or a reference volume")
    if spacing is None:
        raise InputError("spacing (dx, dy, dz) in mm is required for mm axes")
    sp = _vec3(spacing, "spacing", positive=True)
    org = _vec3(origin, "origin")
    rows = []
    if reference is not None:
        rsp = _vec3(reference_spacing, "reference_spacing", True) if reference_spacing is not None else sp
        rorg = _vec3(reference_origin, "reference_origin") if reference_origin is not None else org
        b = volume_bmode(reference, dynamic_range)
        rows.append(("B-mode", b, rsp, rorg, dict(cmap="gray", vmin=-float(dynamic_range), vmax=0.0, norm=None),
                     "echo level (dB)"))
    for k in keys:
        v, cmap, lo, hi, norm, label = _style(k, arrs[k])
        # titles read as the bars' labels do: e_xx, not the key exx
        rows.append((k, v, sp, org, dict(cmap=cmap, vmin=lo, vmax=hi, norm=norm,
                                         title=k[0] + "_" + k[1:] if k in _ORDER[:9] else k), label))
    rows = [dict(name=name, vol=vol, spacing=s, origin=o, label=label, **style)
            for name, vol, s, o, style, label in rows]
    fig, axes_rows = _slice_figure(rows, at, panel_inches)
    if title:
        fig.suptitle(title, fontsize=10)
    fit_colorbars(fig, axes_rows)
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


#: Largest page (inches, width x height) the slices of a volume are scaled to fit, panels with their labels and
#: colour bars: every panel keeps its mm aspect, and the whole is drawn at one scale (inches per mm).
PAGE_INCHES = (15.0, 10.0)
#: The narrowest panel is at least this wide or tall (inches): a volume too thin for the page enlarges it.
MIN_PANEL_INCHES = 0.6
#: A volume's longest extent over its shortest drawn at most this: a shorter axis is stretched to
#: longest / MAX_ASPECT and its axis label says so ("stretched 2.5x"); the 7 MHz matrix probe's 48 x 10 x 8 mm
#: volumes (6.0) are drawn to scale.
MAX_ASPECT = 6.0
#: Names of the three slice orientations, in the order of a quantity's panels.
PLANES = ("axial-lateral", "axial-elevational", "lateral-elevational")
# room (inches) for what is not a panel: the first column's axial tick labels and label, the gap between
# columns (a quantity's panels share their colour bar, so no bar between them), a row of panels' title and
# x tick labels and label, the colour-bar row under the panels and the figure's title
_Y_LABELS_IN, _GAP_IN, _ROW_IN, _BAR_IN, _TITLE_IN = 0.75, 0.2, 0.75, 0.7, 0.45


def _arrangement(L, n_q, page=PAGE_INCHES):
    """How the ``3 n_q`` panels of ``n_q`` quantities of a volume of mm extents ``L`` (x, y, z) are laid out:
    ``(kind, scale in / mm, (width, height) in)``, kind ``"rows"`` (one row per orientation: axial-lateral,
    axial-elevational, lateral-elevational; one column per quantity) or ``"ortho"`` (every quantity a 2 x 2
    block: axial-lateral and axial-elevational side by side sharing depth, lateral-elevational under
    axial-lateral sharing the lateral axis).  The one whose panels come out larger on the ``page`` wins: "rows"
    for shallow and wide volumes, "ortho" for deep and narrow ones, whose axial panels are tall."""
    Lx, Ly, Lz = L
    cand = {"rows": (n_q * max(Ly, Lz), 2 * Lx + Lz, _Y_LABELS_IN + n_q * _GAP_IN, 3 * _ROW_IN),
            "ortho": (n_q * (Ly + Lz), Lx + Lz, _Y_LABELS_IN + 2 * n_q * _GAP_IN, 2 * _ROW_IN)}
    best = None
    for kind, (w_mm, h_mm, w_in, h_in) in cand.items():
        h_in += _BAR_IN + _TITLE_IN
        s = min((page[0] - w_in) / w_mm, (page[1] - h_in) / h_mm)
        s = max(s, MIN_PANEL_INCHES / min(L))
        if best is None or s > best[1] * 1.001:
            best = (kind, s, (s * w_mm + w_in, s * h_mm + h_in))
    return best


def _slice_figure(rows, at, panel_inches):
    """The three orthogonal slices of every quantity (``rows``) through ``at`` (x, y, z) mm (None: the centre of
    the first quantity's grid), laid out by :func:`_arrangement`; returns ``(figure, [[Axes] per figure row])``.
    The figure's ``volume_axes`` maps ``(name, plane)`` (``plane`` of :data:`PLANES`) to the panel's Axes and
    ``volume_colorbars`` every ``name`` to its colour bar (one per quantity, under its panels, its limits shared
    by the three slices).  In every panel dashed lines (gid ``"slice"``) mark where the other two slices cut; the
    titles name the quantity and where the slice lies, the axes are in mm.

    ``rows``: dicts with ``name`` (the key of the panels and bar, and the titles' name unless ``title``), ``vol``
    (nx, ny, nz), ``spacing``, ``origin`` (voxel centres), ``cmap``, ``vmin``, ``vmax``, ``norm`` (a Normalize or
    None), ``label`` (colour bar: quantity and unit), and optionally ``bad`` (colour of NaN voxels, default
    transparent: the background shows through), ``line`` (colour of the dashed lines), ``note`` (a line under the
    first title of the quantity) and ``interpolation`` (imshow's, default "nearest": every voxel drawn as its own
    value).  ``panel_inches``: the longest side of a panel at most this (inches)."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator, NullLocator

    from .plot import colorbar_extend

    shape0, sp0, org0 = rows[0]["vol"].shape, rows[0]["spacing"], rows[0]["origin"]
    if at is None:
        at = tuple(o + 0.5 * (n - 1) * d for o, n, d in zip(org0, shape0, sp0))
    at = _vec3(at, "at")
    plt = _mpl()
    mm = [n * d for n, d in zip(shape0, sp0)]
    # drawn lengths: an axis shorter than 1 / MAX_ASPECT of the longest stretched to it (a 50 x 50 x 5 mm
    # volume's axial slices would be strips, a 100 x 2 x 2 mm one's lateral slices threads)
    stretch = [max(1.0, max(mm) / (MAX_ASPECT * v)) for v in mm]
    L = [v * f for v, f in zip(mm, stretch)]
    nq = len(rows)
    kind, s, _ = _arrangement(L, nq)
    s = min(s, float(panel_inches) / max(L))
    Lx, Ly, Lz = L
    if kind == "rows":
        w_mm, h_mm = nq * max(Ly, Lz), 2 * Lx + Lz
        w_in, h_in = _Y_LABELS_IN + nq * _GAP_IN, 3 * _ROW_IN
        grid = dict(nrows=3, ncols=nq, width_ratios=[max(Ly, Lz)] * nq, height_ratios=[Lx, Lx, Lz])
        cell = lambda q, p: (p, q)                                  # noqa: E731
        col_in = s * max(Ly, Lz)
    else:
        w_mm, h_mm = nq * (Ly + Lz), Lx + Lz
        w_in, h_in = _Y_LABELS_IN + 2 * nq * _GAP_IN, 2 * _ROW_IN
        grid = dict(nrows=2, ncols=2 * nq, width_ratios=[Ly, Lz] * nq, height_ratios=[Lx, Lz])
        cell = lambda q, p: ((0, 2 * q), (0, 2 * q + 1), (1, 2 * q))[p]      # noqa: E731
        col_in = s * (Ly + Lz)
    h_in += _BAR_IN + _TITLE_IN + 0.15 * max(1, max(len(textwrap.wrap(r.get("note") or "", 200)) for r in rows))
    fig = plt.figure(figsize=(s * w_mm + w_in, s * h_mm + h_in), layout="constrained")
    gs = fig.add_gridspec(**grid)
    chars = max(16, int(col_in * 72 / 4.5))         # characters across a quantity's column (7-8 pt text)
    note_chars = max(16, int(s * Ly * 72 / 4.5))     # across its first panel
    grid_rows = [[] for _ in range(grid["nrows"])]
    names = [f"{w} (mm)" + (f"\nstretched {f:.1f}x" if f > 1.0005 else "")
             for w, f in zip(("axial x", "lateral y", "elevational z"), stretch)]
    fig.volume_axes, fig.volume_colorbars = {}, {}
    for q, row in enumerate(rows):
        name, vol, sp, o, label = row["name"], row["vol"], row["spacing"], row["origin"], row["label"]
        i = _index(at[0], o[0], sp[0], vol.shape[0], "x")
        j = _index(at[1], o[1], sp[1], vol.shape[1], "y")
        k = _index(at[2], o[2], sp[2], vol.shape[2], "z")
        c = [o[a] + n * sp[a] for a, n in enumerate((i, j, k))]          # the cuts, mm
        edge = [(o[a] - 0.5 * sp[a], o[a] + (vol.shape[a] - 0.5) * sp[a]) for a in range(3)]
        cmap = plt.get_cmap(row["cmap"]).with_extremes(bad=row.get("bad", (0, 0, 0, 0)))
        kw = dict(cmap=cmap, interpolation=row.get("interpolation", "nearest"))
        if row["norm"] is not None:
            kw["norm"] = row["norm"]
        else:
            kw.update(vmin=row["vmin"], vmax=row["vmax"])
        panels = [   # image, extent, (x, y) axes, where, marker lines (vertical, horizontal)
            (vol[:, :, k], [*edge[1], edge[0][1], edge[0][0]], (1, 0), f"z = {c[2]:.1f} mm", (c[1], c[0])),
            (vol[:, j, :], [*edge[2], edge[0][1], edge[0][0]], (2, 0), f"y = {c[1]:.1f} mm", (c[2], c[0])),
            (vol[i, :, :].T, [*edge[1], *edge[2]], (1, 2), f"x = {c[0]:.1f} mm", (c[1], c[2])),
        ]
        line = row.get("line", "w" if name == "B-mode" else "k")
        images = []
        for p, (img, ext, (ah, av), where, (v, h)) in enumerate(panels):
            r, col = cell(q, p)
            xl, yl = names[ah], names[av]
            ax = fig.add_subplot(gs[r, col])
            # screen length of a mm of y over one of x: 1 but where an axis is stretched
            im = ax.imshow(np.ma.masked_invalid(img), extent=ext, origin="upper" if p < 2 else "lower",
                           aspect=stretch[av] / stretch[ah], **kw)
            images.append(im)
            ax.axvline(v, color=line, lw=0.7, ls="--", alpha=0.7, gid="slice")
            ax.axhline(h, color=line, lw=0.7, ls="--", alpha=0.7, gid="slice")
            ax.set_xlabel(xl, fontsize=8)
            # about one tick label per 0.5 in: five-character labels of a narrow panel would touch
            w_in, h_in = s * stretch[ah] * abs(ext[1] - ext[0]), s * stretch[av] * abs(ext[3] - ext[2])
            ax.xaxis.set_major_locator(MaxNLocator(nbins=max(2, min(6, int(w_in / 0.5))), steps=[1, 2, 5, 10]))
            ax.yaxis.set_major_locator(MaxNLocator(nbins=max(2, min(8, int(h_in / 0.4))), steps=[1, 2, 5, 10]))
            ax.tick_params(labelsize=7)
            # the axial / elevational tick labels once per figure row: panels left of it show the same mm
            if any(b.get_ylabel() == yl and tuple(b.get_ylim()) == tuple(ax.get_ylim()) for b in grid_rows[r]):
                ax.tick_params(labelleft=False)
            else:
                ax.set_ylabel(yl, fontsize=8)
            title = f"{row.get('title', name)}, {where}"
            if p == 0 and row.get("note"):
                title += "\n" + textwrap.fill(row["note"], note_chars)
            ax.set_title(title, fontsize=8)
            grid_rows[r].append(ax)
            fig.volume_axes[(name, PLANES[p])] = ax
        # one bar for the three slices (same norm): the triangle at an end any of them passes
        ends = {colorbar_extend(im) for im in images}
        low = any(e in ("min", "both") for e in ends)
        high = any(e in ("max", "both") for e in ends)
        extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
            low, high]
        label = "\n".join(textwrap.fill(part, chars) for part in label.split("\n"))
        cb = fig.colorbar(images[0], ax=[fig.volume_axes[(name, pl)] for pl in PLANES], location="bottom",
                          extend=extend, extendfrac=0.05, shrink=0.9, aspect=max(8.0, col_in / 0.14))
        cb.set_label(label, fontsize=8)
        cb.ax.tick_params(labelsize=7)
        if row["norm"] is not None and type(row["norm"]).__name__ == "LogNorm":   # plain numbers, not 4 x 10^0
            cb.set_ticks(_log_ticks(row["norm"].vmin, row["norm"].vmax))
            cb.ax.xaxis.set_minor_locator(NullLocator())
            cb.ax.xaxis.set_major_formatter(FuncFormatter(lambda val, _: f"{val:g}"))
        else:
            cb.ax.xaxis.set_major_locator(MaxNLocator(nbins=max(3, int(col_in / 0.6))))
        fig.volume_colorbars[name] = cb
    return fig, [r for r in grid_rows if r]


#: Words that ``at`` of :func:`plot_inversion_volume` takes besides a point.
SLICE_CHOICES = ("centre", "stiffest", "softest")
#: The modulus colour scale of :func:`plot_inversion_volume` spans at least 1 / this to this (median 1).
MIN_MODULUS_SPAN = 1.25
#: Most samples of the picture grid of a 3D inversion (per-element values sampled exactly, a few per element).
_MAX_SAMPLES = 1_500_000


def _element_grid(mesh, per_element):
    """Sampling grid of a tensor hexahedral mesh: ``(locator, points (n, 3), shape, spacing, origin)`` with
    ``per_element`` samples across the thinnest element of each axis (fewer when the grid would exceed
    :data:`_MAX_SAMPLES`); on a uniform axis every sample lies inside one element, so element values are drawn
    with their exact element boundaries."""
    from .volume_fields import HexLocator

    try:
        loc = HexLocator(mesh)
    except InputError:
        raise InputError("pictures of a 3D inversion need an axis-aligned tensor hexahedral mesh (femreg's "
                         "registration and inversion meshes are); write others with to_vtu (ParaView)") from None
    L = np.array([ax[-1] - ax[0] for ax in loc.axes])
    h = np.array([np.diff(ax).min() for ax in loc.axes])
    k = max(1, int(per_element))
    while True:
        n = np.maximum(1, np.round(L / (h / k))).astype(int)
        if np.prod(n) <= _MAX_SAMPLES or k == 1:
            break
        k = max(1, k - 2)                     # an odd count stays odd: element centres remain samples
    spacing = L / n
    origin = np.array([ax[0] for ax in loc.axes]) + 0.5 * spacing
    axes = [origin[a] + spacing[a] * np.arange(n[a]) for a in range(3)]
    X = np.meshgrid(*axes, indexing="ij")
    return loc, np.column_stack([x.ravel() for x in X]), tuple(n), tuple(spacing), tuple(origin)


def _slice_point(result, at, loc):
    """(x, y, z) mm of ``at``: a point, or one of :data:`SLICE_CHOICES`."""
    if at is None or (isinstance(at, str) and at == "centre"):
        # the centre of the element that holds the mesh's centre: a slice through the middle of a layer of
        # elements, not along the faces between two
        out = []
        for ax in loc.axes:
            e = min(int(np.searchsorted(ax, 0.5 * (ax[0] + ax[-1]), side="right")) - 1, ax.size - 2)
            out.append(0.5 * (ax[e] + ax[e + 1]))
        return tuple(out)
    if isinstance(at, str):
        if at not in SLICE_CHOICES:
            raise InputError(f"slice position must be (x, y, z) mm or one of {', '.join(SLICE_CHOICES)}, "
                             f"got {at!r}")
        from scipy.ndimage import label, uniform_filter

        # the region: elements whose mean log mu over their 3 x 3 x 3 neighbourhood (no lone extreme element)
        # reaches half of the extreme, connected to the extreme; the point: the element centre nearest to the
        # region's centroid (weighted by that mean), so that the slices cut the middle of a stiff inclusion.
        # Elements the data do not constrain count as the median (log mu = 0).
        theta = np.log(np.asarray(result.mu, float))
        con = getattr(result, "constrained", None)
        if con is not None and np.size(con) == theta.size:
            theta = np.where(np.asarray(con, bool), theta, 0.0)
        sign = 1.0 if at == "stiffest" else -1.0
        smooth = sign * uniform_filter(theta[loc.cell], size=3, mode="nearest")
        peak = np.unravel_index(np.argmax(smooth), smooth.shape)
        top = smooth[peak]
        if top > 0:
            lab, _ = label(smooth >= 0.5 * top)
            region = lab == lab[peak]
        else:                                   # nothing above the median: the extreme element itself
            region = np.zeros(smooth.shape, bool)
            region[peak] = True
        w = np.where(region, np.maximum(smooth, 0.0), 0.0)
        w = w if w.sum() > 0 else region.astype(float)
        out = []
        for a in range(3):
            centres = 0.5 * (loc.axes[a][1:] + loc.axes[a][:-1])
            c = float(np.sum(w.sum(axis=tuple(b for b in range(3) if b != a)) * centres) / w.sum())
            out.append(float(centres[np.argmin(np.abs(centres - c))]))
        return tuple(out)
    point = _vec3(at, "slice position")
    for a, name in enumerate("xyz"):
        lo, hi = loc.axes[a][0], loc.axes[a][-1]
        if not lo <= point[a] <= hi:
            raise InputError(f"slice position {name} = {point[a]:g} mm lies outside the inversion mesh "
                             f"[{lo:g}, {hi:g}] mm")
    return point


def plot_inversion_volume(result, out_png=None, *, at=None, dpi: int = 100, title=None,
                          samples_per_element: int = 5, panel_inches: float = 8.0):
    r"""Three orthogonal slices of a 3D modulus inversion (:func:`femreg.invert` with ``model="3d"``), drawn as
    :func:`plot_volume_slices` draws a registration: one row each for

    - the relative shear modulus :math:`\mu` / median (log colour scale over 1-99 % of the elements, at least
      1 / :data:`MIN_MODULUS_SPAN` to :data:`MIN_MODULUS_SPAN`), one value per element (the slices show the
      elements' boxes: the blocks are the inversion's resolution, not an artefact of the picture);
    - its uncertainty, the Laplace standard deviation of :math:`\log\mu` per element, with the elements the data
      do not constrain in grey (counted in the row's title); a result without it (a mesh too large for the dense
      Laplace step) gets no such row, and the unconstrained elements are greyed in the modulus row instead;
    - the recovered axial strain :math:`\varepsilon_{xx}` (%) of the displacement the modulus was computed from
      (trilinear between the nodal averages of the element strains, :func:`femreg.volume_fields.
      recovered_strains_3d`).

    Each as three slices, axial-lateral at elevation z, axial-elevational at lateral y, lateral-elevational at
    depth x (mm axes, equal aspect, depth down), with one colour bar under them, laid out as
    :func:`plot_volume_slices` lays them out; dashed lines mark where the other two slices cut.  ``at``: the
    point (x, y, z) mm the slices pass through, or ``"centre"`` (default: the mesh's centre), ``"stiffest"`` /
    ``"softest"`` (the element centre nearest to the centroid of the stiffest / softest region: the elements
    connected to the extreme whose mean log modulus over their 3 x 3 x 3 neighbourhood reaches half of it).
    ``samples_per_element``: picture samples across an element (odd: an element centre is a sample).  A result that
    failed or is flagged gets the red banner of :func:`femreg.plot.draw_failure`.  Writes ``out_png`` when given;
    returns the figure.
    """
    from matplotlib.colors import LogNorm

    from .plot import UNCERTAINTY_ENDS, draw_failure, inversion_banner, uncertainty_range
    from .volume_fields import recovered_strains_3d

    res = result
    if not all(hasattr(res, k) for k in ("mesh", "mu", "u_measured", "model", "beta")) or res.mesh.p.shape[0] != 3:
        raise InputError(f"plot_inversion_volume needs a 3D InversionResult (femreg.load_inversion reads a file), "
                         f"got {type(res).__name__}")
    loc, pts, shape, sp, org = _element_grid(res.mesh, samples_per_element)
    point = _slice_point(res, at, loc)
    _, e, _, _ = loc.locate(pts)
    cell = loc.cell[e[0], e[1], e[2]].reshape(shape)
    n_el = res.mu.size
    mu = np.asarray(res.mu, float)
    unc = getattr(res, "uncertainty", None)
    unc = None if unc is None or np.size(unc) != n_el else np.asarray(unc, float)
    con = getattr(res, "constrained", None)
    con = None if con is None or np.size(con) != n_el else np.asarray(con, bool)
    if unc is not None:
        free = ~np.isfinite(unc) if con is None else (~con | ~np.isfinite(unc))
    else:
        free = np.zeros(n_el, bool) if con is None else ~con
    grey = (0.75, 0.75, 0.75, 1.0)
    note = (f"grey: {int(free.sum())} of {n_el} elements the data do not constrain" if free.any() else None)
    # 1-99 % of the elements, spanning at least 0.8-1.25 around the median (1): a few per cent of variation
    # must not fill the whole colour scale and pass for a contrast
    lo, hi = np.percentile(mu, [1, 99])
    lo, hi = min(lo, 1.0 / MIN_MODULUS_SPAN), max(hi, MIN_MODULUS_SPAN)
    mu_vol = mu[cell]
    rows = [dict(name=r"$\mu$", vol=np.where(free[cell], np.nan, mu_vol) if unc is None else mu_vol,
                 spacing=sp, origin=org, cmap="viridis", vmin=None, vmax=None, norm=LogNorm(lo, hi),
                 label="shear modulus $\\mu$ / median\n(relative, one value per element)", bad=grey,
                 note=note if unc is None else None)]
    if unc is not None:
        u = np.where(free, np.nan, unc)
        ulo, uhi = uncertainty_range(u)
        rows.append(dict(name=r"std of $\log\mu$", vol=u[cell], spacing=sp, origin=org, cmap="magma", vmin=ulo,
                         vmax=uhi, norm=None, bad=grey, line="w", note=note,
                         label="uncertainty: std of $\\log\\mu$\n(-, one value per element)\n" + UNCERTAINTY_ENDS
                         + ("\nNOT calibrated (see notes)" if getattr(res, "uncertainty_calibrated", True) is False
                            else "")))
    um = np.asarray(res.u_measured, float)
    if np.all(np.isfinite(um)) and np.any(um != 0):
        exx = loc.sample(um, pts, nodal_strain=recovered_strains_3d(res.mesh, um))["exx"].reshape(shape)
        label, name = "recovered axial strain\n$\\varepsilon_{xx}$ (%)", r"$\varepsilon_{xx}$"
    else:                                   # no displacement stored: the element-mean strain
        exx = np.asarray(res.strain_measured, float)[:, 0][cell]
        label, name = "axial strain $\\varepsilon_{xx}$ (%)\n(element mean)", r"$\varepsilon_{xx}$"
    cmap, slo, shi = _scale(100.0 * exx)
    # the recovered strain is trilinear: drawn bilinearly between the samples, not as blocks it does not have
    rows.append(dict(name=name, vol=100.0 * exx, spacing=sp, origin=org, cmap=cmap, vmin=slo, vmax=shi, norm=None,
                     label=label, interpolation="bilinear" if "recovered" in label else "nearest"))
    fig, axes_rows = _slice_figure(rows, point, panel_inches)
    head = title or f"{res.model}, beta {res.beta:.3g}, {res.regularization.upper()}"
    if res.success:
        fig.suptitle(head, fontsize=10)
    else:
        # lines that fit the figure (bold 10 pt: about 7.5 pt a character)
        draw_failure(fig, inversion_banner(res, head), width=max(40, int(fig.get_figwidth() * 72 / 7.5)),
                     max_lines=6)
    fit_colorbars(fig, axes_rows)
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def render_volume(fields, spacing, origin=(0.0, 0.0, 0.0), out_png=None, *, key="exx", mode="slices", at=None,
                  iso=None, window_size=None, cmap=None):
    """Off-screen pyvista rendering of one field of a volume, written to ``out_png``.

    ``fields``: dict as :func:`plot_volume_slices` (or one 3D array, named ``key``).  ``mode="slices"``: the
    three orthogonal slices through ``at`` (default centre) in 3D; ``mode="iso"``: the iso-surface(s) of the
    field at ``iso`` (one value or a list, in the drawn unit: % for strain; default the middle of the robust
    range) inside the volume's outline, with the axial-lateral slice at ``at`` for context.  Depth points down,
    lateral to the right, elevation into the screen at an oblique view; NaN voxels are not drawn.
    ``window_size``: pixels (width, height); default 900 x 700, or 700 x 1000 for a volume deeper than 1.5 x its
    wider cross extent (a 48 x 10 x 8 mm one filled a fifth of the landscape window).  Returns the
    Path.  Needs pyvista (``pip install femreg[vtk]``).
    """
    if out_png is None:
        raise InputError("render_volume needs out_png")
    if mode not in ("slices", "iso"):
        raise InputError(f"mode must be 'slices' or 'iso', got {mode!r}")
    arr = fields.get(key) if isinstance(fields, dict) else fields
    if arr is None:
        raise InputError(f"fields has no {key!r} (keys: {', '.join(fields) or 'none'})")
    v, cm, lo, hi, norm, label = _style(key, _volume(arr, key))
    sp = _vec3(spacing, "spacing", positive=True)
    org = _vec3(origin, "origin")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    from .optional import require

    pv = require("pyvista", feature="render_volume")
    pv.OFF_SCREEN = True
    if norm is not None:
        lo, hi = norm.vmin, norm.vmax
    # screen axes: lateral -> X, depth -> -Y (down), elevation -> Z
    nx, ny, nz = v.shape
    grid = pv.ImageData(dimensions=(ny, nx, nz), spacing=(sp[1], sp[0], sp[2]),
                        origin=(org[1], -(org[0] + (nx - 1) * sp[0]), org[2]))
    data = v[::-1].transpose(1, 0, 2)                  # (y, -x, z), depth flipped so that -x increases
    grid.point_data[label] = np.asfortranarray(data).ravel(order="F")
    centre = [o + 0.5 * (n - 1) * d for o, n, d in zip(org, v.shape, sp)]
    a = _vec3(at, "at") if at is not None else tuple(centre)
    if window_size is None:
        L = [n * d for n, d in zip(v.shape, sp)]
        window_size = (700, 1000) if L[0] > 1.5 * max(L[1], L[2]) else (900, 700)
    # the bar's title (about 150 px) centred on it: inside a narrow window too
    bar = {"title": label, "vertical": True, "position_x": 0.86 if window_size[0] >= 900 else 0.8,
           "position_y": 0.1, "height": 0.8,
           "title_font_size": 14, "label_font_size": 12}
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        plotter.set_background("white")
        plotter.add_mesh(grid.outline(), color="black")
        kw = dict(scalars=label, cmap=cmap or cm, clim=(lo, hi), nan_opacity=0.0, scalar_bar_args=bar,
                  log_scale=norm is not None)
        if mode == "slices":
            plotter.add_mesh(grid.slice_orthogonal(x=a[1], y=-a[0], z=a[2]), **kw)
        else:
            finite = data[np.isfinite(data)]
            if iso is None:
                iso = [0.5 * (np.percentile(finite, 5) + np.percentile(finite, 95))] if finite.size else []
            levels = [float(t) for t in np.atleast_1d(iso)]
            filled = grid.copy()
            filled.point_data[label] = np.nan_to_num(grid.point_data[label],
                                                     nan=float(np.median(finite)) if finite.size else 0.0)
            surf = filled.contour(levels, scalars=label)
            if surf.n_points:
                plotter.add_mesh(surf, **dict(kw, scalar_bar_args=bar))
            plotter.add_mesh(grid.slice(normal="z", origin=(a[1], -a[0], a[2])), opacity=0.5,
                             **dict(kw, show_scalar_bar=not surf.n_points))
        plotter.show_bounds(xtitle="lateral y (mm)", ytitle="-depth x (mm)", ztitle="elevation z (mm)",
                            color="black", font_size=10)
        plotter.view_xy()
        plotter.camera.azimuth = -30
        plotter.camera.elevation = 20
        plotter.reset_camera()                 # refit the rotated box: its bounds labels inside the window
        plotter.camera.zoom(0.9)
        plotter.screenshot(str(out_png))
    finally:
        plotter.close()
    return Path(out_png)
