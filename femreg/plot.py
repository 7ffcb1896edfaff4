"""Figures: B-mode images, pixel-grid fields (displacement, strain) with colour bars and mm axes, a summary
figure of a registration result, and an off-screen pyvista render of the FE mesh coloured by a field.

Axes: lateral y (mm) horizontal, axial x (mm) vertical and increasing downwards (depth), as on a scanner.
The panels (:func:`plot_bmode`, :func:`plot_field`, :func:`plot_mesh_values`) take ``ax=`` (a new figure when
None) and return the Axes; the whole figures (:func:`plot_result`, :func:`plot_inversion`, :func:`plot_quality`,
which takes ``ax=`` too) return the Figure, written to ``out_png`` when given.

Conventions of the figures femreg writes: strain in % and displacement in mm, the unit on every colour bar; a
sequential colour map (bright = large magnitude) for data of one sign and a diverging one centred at 0 only when
both signs carry a meaningful share of the robust range (percentiles 1-99, :func:`colour_scale`); a failed registration says so
in a red banner with its message; the part of the image outside the registered mesh is hatched and labelled.
"""
from __future__ import annotations

import os
import textwrap
from pathlib import Path

import numpy as np

from .errors import InputError, pass_as

__all__ = ["bmode", "plot_bmode", "plot_field", "plot_result", "render_mesh", "extent_mm", "colour_scale",
           "plot_inversion", "plot_mesh_values", "plot_quality", "plot_shear", "fit_colorbars", "DIVERGING_CMAP",
           "SEQUENTIAL_CMAP", "SIGNED_SHARE"]

#: Colour maps: diverging for signed data (centred at 0), sequential for one-signed data; for negative data the
#: sequential map is reversed, so that a larger magnitude (e.g. more compression: softer tissue) is brighter.
DIVERGING_CMAP = "RdBu_r"
SEQUENTIAL_CMAP = "viridis"
_DIVERGING = ("RdBu_r", "RdBu", "seismic", "bwr", "coolwarm", "PuOr", "PiYG")


#: Least share of the larger end a robust end of the other sign must reach for the diverging map: below it the
#: other sign is a sliver (e.g. an axial displacement negative almost everywhere whose 99th percentile is 2 % of
#: its 1st), for which symmetric limits would leave about half the colour bar unused.
SIGNED_SHARE = 0.15
#: Characters per line of a result figure's footer (the hatching's note and what was left out).
SUPXLABEL_WIDTH = 150


def colour_scale(values, percentiles=(1.0, 99.0)):
    """Colour map and limits for ``values`` (any shape, NaN ignored): ``(cmap, vmin, vmax)``.

    The robust range ``[lo, hi]`` is the given percentiles of the finite values.  When both signs carry a
    meaningful share of it (``lo < 0 < hi`` and ``min(-lo, hi) >= SIGNED_SHARE * max(-lo, hi)``) the map is
    :data:`DIVERGING_CMAP` with limits symmetric about 0; otherwise :data:`SEQUENTIAL_CMAP` over ``[lo, hi]``
    (reversed, ``"_r"``, for data mostly negative: ``-lo > hi``).  No finite value: the diverging map over
    [-1, 1].
    """
    v = np.asarray(values, float)
    finite = v[np.isfinite(v)]
    if not finite.size:
        return DIVERGING_CMAP, -1.0, 1.0
    lo, hi = (float(q) for q in np.percentile(finite, percentiles))
    if lo < 0.0 < hi and min(-lo, hi) >= SIGNED_SHARE * max(-lo, hi):
        m = max(-lo, hi)
        return DIVERGING_CMAP, -m, m
    if hi <= lo:                                   # constant data
        pad = abs(lo) * 0.05 or 1.0
        lo, hi = lo - pad, hi + pad
    return (SEQUENTIAL_CMAP + "_r" if -lo > hi else SEQUENTIAL_CMAP), lo, hi


def _mpl():
    import matplotlib

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _image2d(a, name):
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2 or min(arr.shape) < 2:
        flat = (" (one value per pixel point: the image's shape is the result's, e.g. res.on_grid()['exx'] or "
                "values.reshape(res.shape))" if arr.ndim == 1 else "")
        raise InputError(f"{name} must be a 2D (axial, lateral) array, got shape {arr.shape}{flat}")
    return arr


#: An image without an RF carrier whose mean exceeds this many standard deviations is log-compressed already (a
#: scanner's display B-mode: mean / std 5-10 for 50-60 dB of grey levels); an envelope's amplitude is about 1.9
#: (Rayleigh speckle) and at most about 3 with a noise floor.
LOG_COMPRESSED_RATIO = 4.0


def bmode(rf, dynamic_range=50.0, *, reference=None):
    """Log-compressed envelope of RF (axial along axis 0) in dB, clipped to ``[-dynamic_range, 0]``.

    Envelope = ``|hilbert(rf, axis=0)|`` (:func:`femreg.speckle.envelope`); 0 dB is its maximum (or ``reference``
    if given, e.g. to put several frames on one scale).  Frames without a carrier
    (:func:`femreg.orientation.is_envelope`) are taken as they are: an envelope's amplitude is log-compressed, a
    B-mode already log-compressed (negative values, or a mean above :data:`LOG_COMPRESSED_RATIO` standard
    deviations: display grey levels) is mapped linearly from its darkest 0.5 % to its maximum.  Returns float64
    (axial, lateral).
    """
    from .speckle import envelope

    arr = _image2d(rf, "rf")
    if not np.all(np.isfinite(arr)):
        raise InputError("rf contains NaN/Inf")
    if not (np.isfinite(dynamic_range) and dynamic_range > 0):
        raise InputError(f"dynamic_range must be positive (dB), got {dynamic_range!r}")
    from .orientation import is_envelope

    if is_envelope(arr):
        if arr.min() < 0 or float(np.mean(arr)) > LOG_COMPRESSED_RATIO * float(np.std(arr)):
            # log-compressed already (dB, or a scanner's display grey levels): its levels as they are, from the
            # darkest 0.5 % to the brightest mapped onto [-dynamic_range, 0]
            lo, hi = float(np.percentile(arr, 0.5)), float(arr.max())
            if not hi > lo:
                return np.full(arr.shape, -float(dynamic_range))
            return np.clip((arr - hi) / (hi - lo) * float(dynamic_range), -float(dynamic_range), 0.0)
        env = np.abs(arr)                           # an envelope already: its amplitude
    else:
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


def _colorbar(ax, mappable, label):
    """A colour bar exactly as tall as the (aspect-locked) image, right of it, labelled with quantity and unit;
    a triangle at an end whose limit the data pass (:func:`colorbar_extend`), so saturated colours are not read
    as values."""
    extend = colorbar_extend(mappable)
    # the triangles (5 % of the bar each) stand beyond the image's top / bottom: the bar itself keeps its height
    lo, hi = (_EXTEND_FRAC * (extend in ends) for ends in (("min", "both"), ("max", "both")))
    cax = ax.inset_axes([1.03, -lo, 0.045, 1.0 + lo + hi])
    cb = ax.figure.colorbar(mappable, cax=cax, label=label or "", extend=extend, extendfrac=_EXTEND_FRAC)
    title = ax.get_title()
    if hi and title and "\n" not in title:
        # a one-line title clears the triangle (right of the image): kept level with the row's other titles
        ax.set_title(title, y=1.0)
    return cb


#: Length of a colour bar's end triangle, as a fraction of the bar.
_EXTEND_FRAC = 0.05


def colorbar_extend(mappable) -> str:
    """Which ends of ``mappable``'s colour limits its finite data pass (by more than 1e-6 of the range): "neither",
    "min", "max" or "both", matplotlib's ``extend``."""
    data = mappable.get_array()
    vmin, vmax = mappable.norm.vmin, mappable.norm.vmax
    if data is None or vmin is None or vmax is None:
        return "neither"
    data = np.ma.filled(np.ma.masked_invalid(np.ma.asarray(data, float)), np.nan)
    finite = data[np.isfinite(data)]
    if finite.size == 0:
        return "neither"
    tol = 1e-6 * max(abs(vmax - vmin), 1e-300)
    low, high = bool(finite.min() < vmin - tol), bool(finite.max() > vmax + tol)
    return {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[low, high]


#: Clear margin (inches) between the outermost labels and the figure's edge; a failed result's red frame
#: (:func:`draw_failure`, 6 pt wide, half of it inside the figure) adds its own width.
EDGE_MARGIN_IN = 0.05


def fit_colorbars(fig, rows, tries=10):
    """Widen the gaps between panels until no colour bar (an inset of its panel, which the layout engine does not
    reserve room for) with its label reaches the next panel's axis label in its row, and pull the panels in from
    the figure's edges until the last colour bar's label and the first axis label lie inside it, clear of a red
    failure frame.  ``fig``: a figure with constrained layout; ``rows``: lists of Axes left to right.  Call it
    last, before saving: once the labels fit, the layout is kept as checked (the layout engine is set to "none"),
    so that saving or drawing the figure does not lay it out again (about a quarter of a summary figure's time)
    nor move what was checked."""
    engine = fig.get_layout_engine()
    if engine is None or not hasattr(engine, "set"):
        return
    wspace = 0.02
    rect = [0.0, 0.0, 1.0, 1.0]
    margin = (EDGE_MARGIN_IN + getattr(fig, "_femreg_frame_in", 0.0)) * fig.dpi     # px
    _wrap_suptitle(fig, margin)
    for _ in range(tries):
        fig.draw_without_rendering()   # the layout and every extent as a draw makes them, no pixels
        r = fig.canvas.get_renderer()
        need = 0.0
        for row in rows:
            for left, right in zip(row[:-1], row[1:]):
                if not left.child_axes:
                    continue
                reach = max(c.get_tightbbox(r).x1 for c in left.child_axes)
                need = max(need, reach + 0.15 * fig.dpi - right.get_tightbbox(r).x0)   # 0.15 in clear
        boxes = [b for ax in fig.axes for b in [ax.get_tightbbox(r)] + [c.get_tightbbox(r) for c in ax.child_axes]
                 if b is not None]
        w, h = fig.bbox.width, fig.bbox.height
        over = (max(0.0, margin - min(b.x0 for b in boxes)), max(0.0, max(b.x1 for b in boxes) - (w - margin)),
                max(0.0, margin - min(b.y0 for b in boxes)))
        if need <= 0 and max(over) <= 0.5:
            fig.set_layout_engine("none")
            return
        if need > 0:
            wspace += 1.2 * need / w * len(rows[0])
        # inset colour bars lie outside what the layout places: shrink its rectangle by what sticks out
        rect[0] += 1.1 * over[0] / w
        rect[2] -= 1.1 * (over[0] + over[1]) / w
        rect[1] += 1.1 * over[2] / h
        rect[3] -= 1.1 * over[2] / h
        engine.set(wspace=wspace, rect=tuple(rect))


def _wrap_suptitle(fig, margin_px: float) -> None:
    """Wrap the figure's title onto as many lines as keep it inside the figure, ``margin_px`` from its edges: one
    line of a track frame's title (frames, regulariser, alpha, NCC of the last step) ran past both edges of a
    three-panel figure, its first and last words cut off."""
    t = getattr(fig, "_suptitle", None)
    if t is None or not t.get_text():
        return
    r = fig.canvas.get_renderer()
    room = fig.bbox.width - 2.0 * margin_px
    for _ in range(3):
        width = t.get_window_extent(r).width
        if width <= room:
            return
        text = " ".join(t.get_text().split())
        longest = max(len(line) for line in t.get_text().splitlines())
        # whole words only: a break after a hyphen ("plane-" / "stress") would change the words a reader greps
        t.set_text(textwrap.fill(text, max(20, int(longest * room / width) - 2), break_on_hyphens=False,
                                 break_long_words=False))


#: How a B-mode is drawn on a pixel grid: a full-depth frame holds several samples per screen pixel (2000 rows in
#: about 330), and picking the nearest one aliases the speckle into pixel-sized salt-and-pepper noise; matplotlib's
#: anti-aliasing filter averages them (nearest where the image is enlarged).
_BMODE_IMSHOW = {"interpolation": "antialiased"}


def _draw(ax, img, ext, positions, **kw):
    """imshow of a pixel-grid image, or (``positions`` = physical (X, Y) of every sample of a convex / sector
    frame, :mod:`femreg.geometry`) a scan-converted pcolormesh at the samples' physical positions."""
    if positions is None:
        return ax.imshow(img, extent=ext, **{"interpolation": "nearest", **kw})
    X, Y = positions
    kw.pop("interpolation", None)                  # pcolormesh draws each sample's cell
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
               aspect=aspect, **_BMODE_IMSHOW)
    _label(ax, title)
    if colorbar:
        _colorbar(ax, im, "echo level (dB)")
    return ax


def plot_field(field, spacing, origin=(0.0, 0.0), ax=None, *, title=None, cmap=None, vmin=None, vmax=None,
               overlay_bmode=None, alpha=0.7, label=None, dynamic_range=50.0, aspect="equal", symmetric=None,
               scale=1.0, positions=None):
    """A pixel-grid field (NaN = outside the mesh, left transparent) with mm axes and a colour bar.

    ``overlay_bmode``: RF of the same shape drawn as a grey B-mode beneath the field, which is then drawn with
    opacity ``alpha``.  ``scale`` multiplies the field before drawing (100: a strain fraction drawn in %; ``label``
    names the quantity and its unit for the colour bar).  ``cmap=None``: chosen from the data by
    :func:`colour_scale` (sequential for one sign, diverging centred at 0 when both signs matter); an explicit
    ``cmap`` has limits from the robust percentiles (1, 99), symmetric about 0 for diverging maps
    (``symmetric=None`` decides from ``cmap``).  ``positions``: physical (X, Y) of the samples of a convex /
    sector frame (scan-converted, :mod:`femreg.geometry`).  Returns the Axes.
    """
    sp = _spacing(spacing)
    f = _image2d(field, "field") * float(scale)
    ax = _ax(ax)
    ext = extent_mm(f.shape, sp, origin)
    if overlay_bmode is not None:
        b = _image2d(overlay_bmode, "overlay_bmode")
        if b.shape != f.shape:
            raise InputError(f"overlay_bmode shape {b.shape} differs from the field's {f.shape}")
        _draw(ax, bmode(b, dynamic_range), ext, positions, cmap="gray", vmin=-dynamic_range, vmax=0,
              aspect=aspect, **_BMODE_IMSHOW)
    if cmap is None and symmetric is None:
        cmap, lo, hi = colour_scale(f)
    else:
        cmap = cmap or DIVERGING_CMAP
        finite = f[np.isfinite(f)]
        if symmetric is None:
            symmetric = cmap in _DIVERGING
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
    _colorbar(ax, im, label)
    return ax


#: (key, panel title, colour-bar label with unit, scale to that unit) of the summary figure's field panels.
_PANELS = (("ux", "axial displacement $u_x$", "axial displacement $u_x$ (mm)", 1.0),
           ("uy", "lateral displacement $u_y$", "lateral displacement $u_y$ (mm)", 1.0),
           ("exx", "axial strain $\\varepsilon_{xx}$", "axial strain $\\varepsilon_{xx}$ (%)", 100.0),
           ("eyy", "lateral strain $\\varepsilon_{yy}$", "lateral strain $\\varepsilon_{yy}$ (%)", 100.0),
           ("exy", "shear strain $\\varepsilon_{xy}$", "shear strain $\\varepsilon_{xy}$ (%)", 100.0))
#: Colour of the failure banner and frame.
FAILED_COLOUR = "#c00000"


#: A strain colour range narrower than this fraction of the mean strain is said in the panel's title.
NARROW_SPAN = 0.2


def span_note(lo, hi, mean) -> str:
    """``"\ncolours span N % of the mean strain"`` where a strain panel's colour range ``lo``-``hi`` is under
    :data:`NARROW_SPAN` of ``mean`` (its mean magnitude, same units), else "": full-scale colours over a few percent
    read as strong contrast (a 15 MHz pair: -0.74 to -0.78 % drawn from yellow to purple where the truth's stiff
    nodule spans a factor 2; its elastogram 0.975-1.03 of the mean)."""
    mean = abs(float(mean))
    if not mean > 0 or (hi - lo) >= NARROW_SPAN * mean:
        return ""
    return f"\ncolours span {100 * (hi - lo) / mean:.1f} % of the mean strain"


def narrow_span_note(exx) -> str:
    """:func:`span_note` of the axial strain panel of :func:`plot_result`: ``exx``'s robust 1-99 % percentiles (as
    :func:`plot_field` draws it) against its mean."""
    e = np.asarray(exx, float)
    finite = e[np.isfinite(e)]
    if finite.size < 2:
        return ""
    lo, hi = np.percentile(finite, [1, 99])
    return span_note(lo, hi, np.mean(finite))


def _attr(result, d, key):
    """``result.key`` (an engine object) or ``d[key]`` (a file's dict), None when neither has it."""
    v = getattr(result, key, None)
    if v is None:
        v = d.get(key)
    if isinstance(v, np.ndarray) and v.ndim == 0:
        v = v.item()
    return None if (v is None or (isinstance(v, str) and not v.strip())) else v


def _status(result, d):
    """(failed, banner text) of a result: failed when ``success`` is present and false, or it is flagged."""
    msg = str(_attr(result, d, "message") or "").strip()
    success = _attr(result, d, "success")
    flags = _attr(result, d, "flags")
    flags = [str(f) for f in np.atleast_1d(flags) if str(f).strip()] if flags is not None else []
    if success is not None and not bool(success):
        return True, "REGISTRATION FAILED" + (f": {msg.removeprefix('FAILED: ')}" if msg else "")
    if flags:
        return True, "FLAGGED: " + "; ".join(flags[:2])
    return False, ""


def _wrap(text, width=110, max_lines=3):
    import textwrap

    lines = textwrap.wrap(text, width)
    if max_lines is None:
        return "\n".join(lines)
    return "\n".join(lines[:max_lines]) + (" ..." if len(lines) > max_lines else "")


def flag_gist(text: str) -> str:
    """A flag without its parenthesised detail (numbers, the optimiser's message): the sentence a banner has room
    for; the whole text stays in the result's message and the command's output."""
    out, depth = [], 0
    for ch in str(text).replace("(s)", "s"):
        if ch == "(":
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif not depth:
            out.append(ch)
    gist = " ".join("".join(out).split())
    for a, b in ((" :", ":"), (" ,", ","), (" ;", ";"), (" .", ".")):
        gist = gist.replace(a, b)
    return gist.strip(" ,;:")


def inversion_banner(res, head: str) -> str:
    """Banner text of a failed or flagged :class:`femreg.inversion.InversionResult` (2D and 3D pictures): every
    flag's gist (:func:`flag_gist`), one after another, so that a long first flag does not hide the others behind
    the banner's last line (the whole text is in the message); ``head`` (model, beta) in brackets."""
    msg = str(res.message)
    kind = "FLAGGED" if msg.startswith("FLAGGED") else "FAILED"
    flags = [str(f) for f in (getattr(res, "flags", None) or []) if str(f).strip()]
    why = (" | ".join(flag_gist(f) for f in flags) if flags
           else msg.removeprefix("FAILED: ").removeprefix("FLAGGED: "))
    return f"INVERSION {kind}: {why}  [{head}]"


def draw_failure(fig, text, width=110, max_lines=3):
    """Red banner (the figure's title) with ``text`` (lines of at most ``width`` characters, at most
    ``max_lines`` of them, None: all) and a red frame around the figure: a failed result must not pass for a good
    one when the PNG travels without its log."""
    from matplotlib.patches import Rectangle

    fig.suptitle(_wrap(text, width, max_lines), color="white", fontweight="bold", fontsize="medium",
                 bbox=dict(boxstyle="square,pad=0.4", facecolor=FAILED_COLOUR, edgecolor="none"))
    fig.patches.append(Rectangle((0.0, 0.0), 1.0, 1.0, transform=fig.transFigure, fill=False,
                                 edgecolor=FAILED_COLOUR, linewidth=6, zorder=100))
    fig._femreg_frame_in = 6 / 72 / 2          # the frame's inner half (inches): fit_colorbars keeps labels clear


def _roi_rectangle(result, d):
    """(x0, x1, y0, y1) mm of the registered region: ``roi`` of the result when it has one, else the bounding box
    of the mesh."""
    roi = _attr(result, d, "roi")
    if roi is not None:
        r = np.asarray(roi, float).ravel()
        if r.size == 4 and np.all(np.isfinite(r)):
            return tuple(r)
    p = np.asarray(d["mesh_points"], float)
    return (p[0].min(), p[0].max(), p[1].min(), p[1].max())


def _shade_outside(ax, outside, spacing, origin, roi, label=None, positions=None):
    """Hatch the pixels of ``outside`` (bool (n_axial, n_lateral)), outline ``roi`` (x0, x1, y0, y1) mm, and write
    ``label`` in the widest outside strip when it has room.  ``positions``: the samples' physical (X, Y) of a
    convex / sector frame: the samples are hatched there (no rectangle: the mesh is an annular sector)."""
    from matplotlib.patches import Rectangle

    if not outside.any():
        return
    if positions is not None:
        with np.errstate(all="ignore"):
            ax.contourf(positions[1], positions[0], outside.astype(float), levels=[0.5, 1.5],
                        colors=[(0.55, 0.55, 0.55, 0.55)], hatches=["///"], zorder=3)
        return
    n_ax, n_lat = outside.shape
    x = origin[0] + spacing[0] * np.arange(n_ax)
    y = origin[1] + spacing[1] * np.arange(n_lat)
    with np.errstate(all="ignore"):
        ax.contourf(y, x, outside.astype(float), levels=[0.5, 1.5], colors=[(0.55, 0.55, 0.55, 0.55)],
                    hatches=["///"], zorder=3)
    x0, x1, y0, y1 = roi
    ax.add_patch(Rectangle((y0, x0), y1 - y0, x1 - x0, fill=False, edgecolor="k", linestyle="--", linewidth=0.8,
                           zorder=4))
    if not label:
        return
    ext = extent_mm(outside.shape, spacing, origin)          # left, right, bottom (deep), top
    strips = {"top": (x0 - ext[3], ((ext[0] + ext[1]) / 2, (ext[3] + x0) / 2), 0),
              "bottom": (ext[2] - x1, ((ext[0] + ext[1]) / 2, (x1 + ext[2]) / 2), 0),
              "left": (y0 - ext[0], ((ext[0] + y0) / 2, (ext[2] + ext[3]) / 2), 90),
              "right": (ext[1] - y1, ((y1 + ext[1]) / 2, (ext[2] + ext[3]) / 2), 90)}
    depth, width = ext[2] - ext[3], ext[1] - ext[0]
    name, (size, (ty, tx), rot) = max(strips.items(), key=lambda kv: kv[1][0] / (depth if kv[1][2] == 0 else width))
    if size < 0.08 * (depth if rot == 0 else width):
        return
    bb = ax.get_window_extent()                    # pixels; about 6 pixels per character at x-small
    room = (bb.width if rot == 0 else bb.height) * 72.0 / ax.figure.dpi / 5.0
    ax.text(ty, tx, _wrap(label, max(int(room), 12), 3), ha="center", va="center", rotation=rot,
            fontsize="x-small", zorder=5,
            bbox=dict(boxstyle="round,pad=0.2", facecolor="white", alpha=0.85, edgecolor="none"))


def plot_result(result, out_png=None, *, reference=None, overlay=False, dpi=100, dynamic_range=50.0,
                figsize=None, bmode_title="B-mode"):
    """Summary figure of a registration result: B-mode (if ``reference`` RF, or a ``reference``/``rf`` key in
    the result, is available; the mesh otherwise) and ux, uy (mm), exx, eyy, exy (%) on the pixel grid.

    Colour maps by :func:`colour_scale`; a failed (``success`` false) or flagged result gets a red banner with its
    message; pixels outside the registered mesh are hatched on every panel, the registered rectangle (the result's
    ``roi`` (x0, x1, y0, y1) mm when it has one, else the mesh's bounding box) dashed, and the B-mode panel names
    why (the result's ``excluded`` text when it has one).

    Parameters
    ----------
    result : path to a result .npz, a dict, or an engine result object (see :mod:`femreg.io.results`).
    out_png : path, optional
        Where to save the figure (PNG).  The figure is returned either way.
    reference : (axial, lateral) RF of the reference image, optional.
    overlay : draw each field over the B-mode.
    bmode_title : the B-mode panel's title (which frame it shows).
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
            swapped = ("; its axes are the grid's exchanged: frames stored lines first, transpose them ("
                       + pass_as("CLI: --transpose", "--transpose") + ")"
                       if reference.shape == tuple(shape)[::-1] else "")
            raise InputError(f"reference shape {reference.shape} differs from the result grid {shape}{swapped}")
    positions = _beam_positions(result, d, shape, sp, origin)
    plt = _mpl()
    n_ax, n_lat = shape
    aspect_ratio = (n_ax * sp[0]) / max(n_lat * sp[1], 1e-12)
    if positions is not None:
        aspect_ratio = float(np.ptp(positions[0]) / max(np.ptp(positions[1]), 1e-12))
    if figsize is None:
        w = 3.6                      # per panel; about 1.4 in of it go to the colour bar and the labels
        figsize = (3 * w, 2 * min(max((w - 1.4) * aspect_ratio + 1.0, 2.5), 6.5) + 0.5)
    fig, axes = plt.subplots(2, 3, figsize=figsize, constrained_layout=True)
    axes = axes.ravel()
    aspect = "equal" if 0.2 < aspect_ratio < 5 else "auto"  # very tall/flat grids fill the panel
    if reference is not None:
        plot_bmode(reference, sp, origin, ax=axes[0], dynamic_range=dynamic_range, aspect=aspect,
                   positions=positions, title=bmode_title)
    else:
        p, t, _ = check_mesh(d["mesh_points"], d["mesh_cells"], d["u"])
        ax = axes[0]
        from matplotlib.collections import PolyCollection

        polys = np.stack([p[1][t].T, p[0][t].T], axis=-1)  # (n_el, 4, [y, x])
        ax.add_collection(PolyCollection(polys, facecolor="none", edgecolor="k", linewidth=0.3))
        # a fan: the field panels' limits (the whole fan, as _draw sets them), so the panels line up
        ext = extent_mm(shape, sp, origin) if positions is None else (
            np.min(positions[1]), np.max(positions[1]), np.max(positions[0]), min(np.min(positions[0]), 0.0))
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect(aspect)
        _label(ax, f"mesh ({t.shape[1]} quads)")
    for ax, (key, title, label, scale) in zip(axes[1:], _PANELS):
        title += narrow_span_note(d[key]) if key == "exx" else ""
        plot_field(d[key], sp, origin, ax=ax, title=title, label=label, scale=scale,
                   overlay_bmode=reference if overlay else None, aspect=aspect, dynamic_range=dynamic_range,
                   positions=positions)
    for ax in (axes[1], axes[2], axes[4], axes[5]):
        ax.set_ylabel("")                                   # one depth label per row, at the left
    outside = ~np.isfinite(np.asarray(d["ux"], float))
    if outside.any():
        excluded = _attr(result, d, "excluded")
        roi = _roi_rectangle(result, d)
        for i, ax in enumerate(axes):
            _shade_outside(ax, outside, sp, origin, roi,
                           label=(str(excluded) if excluded else "not registered (outside the mesh)")
                           if i == 0 else None, positions=positions)
        # wrapped: an exclusion's reason (a fan's fill) runs past the figure's edges on one line
        fig.supxlabel(textwrap.fill("hatched: outside the registered mesh (no displacement or strain there)"
                                    + (f"; {excluded}" if excluded else ""), SUPXLABEL_WIDTH), fontsize="small")
    info = []
    if "regularizer" in d:
        info.append(f"regulariser {d['regularizer']}")
    if "alpha" in d:
        info.append(f"alpha {float(d['alpha']):.3g}")
    step = ""
    pair = np.ravel(d["pair"]) if d.get("pair") is not None else np.empty(0)
    if pair.size == 2 and "frame" not in d:        # a pair of `femreg register --pair I J` or `femreg batch`
        info.insert(0, f"frames {int(pair[0])} -> {int(pair[1])}")
    if "frame" in d and "increment" in d:          # a frame of `femreg track`: say what the picture accumulates
        k = int(d["frame"])
        accumulated = str(d["mode"]) != "direct" if "mode" in d else True
        info.insert(0, f"frame 0 -> {k}" + (" (accumulated)" if accumulated and k > 1 else ""))
        step = f"frame {k - 1} -> {k}, " if accumulated and k > 1 else ""
    if "ncc_before" in d and "ncc_after" in d:
        info.append(f"NCC {float(d['ncc_before']):.3f} -> {float(d['ncc_after']):.3f} ({step}before -> after)")
    failed, banner = _status(result, d)
    if failed:
        draw_failure(fig, banner + ("  [" + ", ".join(info) + "]" if info else ""))
    elif info:
        fig.suptitle(", ".join(info))
    fit_colorbars(fig, [list(axes[:3]), list(axes[3:])])
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def _beam_positions(result, d, shape, spacing, origin):
    """Physical (X, Y) of the samples when ``result`` is a convex / sector result (its ``sample_positions``, or
    the ``geometry_*`` keys of its file), else None."""
    if hasattr(result, "sample_positions"):
        return result.sample_positions()
    from .io.results import beam_geometry

    geo = beam_geometry(d)
    return None if geo is None else geo.sample_positions(shape, spacing, origin)


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
    from .optional import require

    pv = require("pyvista", feature="render_mesh")

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
def _plain_tick(v, _pos=None) -> str:
    """A log colour bar's tick as a plain number: 0.1, 2.5, 1.25, 100 (``:.2g`` alone writes 100 as 1e+02, and
    1.25 as 1.2)."""
    text = f"{v:.3g}"
    return f"{v:.0f}" if "e+" in text else text


#: Least span of an uncertainty colour scale (std of log mu, -): 0.05, about 5 % of mu, so a nearly uniform
#: uncertainty is not stretched over the whole scale and read as a pattern.
UNCERTAINTY_MIN_SPAN = 0.05
#: What the uncertainty colour bar's ends mean, beside its quantity.
UNCERTAINTY_ENDS = "low: more certain, high: less certain"


def uncertainty_range(unc) -> tuple:
    """Colour limits of an uncertainty map (std of log mu per element, -): 1-99 % of its finite values, not 0 --
    the dark end at 0 would stand for a certain element, which none is -- widened to
    :data:`UNCERTAINTY_MIN_SPAN` about their middle, never below 0."""
    v = np.asarray(unc, float).ravel()
    v = v[np.isfinite(v)]
    if not v.size:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(v, [1, 99]))
    if hi - lo < UNCERTAINTY_MIN_SPAN:
        lo = max(0.0, 0.5 * (lo + hi) - 0.5 * UNCERTAINTY_MIN_SPAN)
        hi = lo + UNCERTAINTY_MIN_SPAN
    return lo, hi


#: Least colour range of the shear map's element width in lateral speckle cells (log scale, around 1).
CELLS_RANGE = (0.5, 4.0)


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
    if ax is None:
        # the figure shaped as the mesh (a convex fan is wider than deep): about 1.4 in of its width go to the
        # colour bar and the labels, 1.2 in of its height to the title and the axis label
        depth, width = float(np.ptp(p[0])), float(np.ptp(p[1]))
        h = 3.6 * depth / width + 1.2 if width > 0 else 6.0
        ax = _ax(None, figsize=(5.0, float(np.clip(h, 2.5, 8.0))))
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
    cb = _colorbar(ax, pc, label)
    if log:                                         # plain numbers (0.5, 2, 4), not powers of ten
        from matplotlib.ticker import FuncFormatter

        fmt = FuncFormatter(_plain_tick)
        cb.ax.yaxis.set_major_formatter(fmt)
        inner = _log_ticks(lo, hi) if hi / lo < 10 else []
        if hi / lo < 10 and len(inner) < 3:         # within a decade the minor ticks are the only labels;
            cb.ax.yaxis.set_minor_formatter(fmt)    # across decades labelling them would overprint
        elif hi / lo < 10:
            from matplotlib.ticker import NullFormatter

            # 0.88-1.68 x the median (a stiff lesion) was labelled 0.9 and 1 only: nothing near the lesion's value
            cb.set_ticks(inner)
            cb.ax.yaxis.set_major_formatter(fmt)
            cb.ax.yaxis.set_minor_formatter(NullFormatter())
        else:
            from matplotlib.ticker import NullFormatter

            # decades alone left 0.17-86 labelled 1 and 10 only: round values near both ends too
            cb.set_ticks(_log_ticks(lo, hi))
            cb.ax.yaxis.set_major_formatter(fmt)
            cb.ax.yaxis.set_minor_formatter(NullFormatter())
    return ax


def _log_ticks(lo, hi, n=6):
    """Round values in [lo, hi] for a log colour bar, at least about 1/n of the range apart on the log scale
    (their labels cannot overlap): 1 when in range, then mantissas 2 and 5, 3 and 4, 1.5, 2.5 and 8, others."""
    lo, hi = float(lo), float(hi)
    rank = {1: 0, 2: 1, 5: 1, 3: 2, 4: 2, 1.5: 3, 2.5: 3, 8: 3, 6: 4, 1.25: 4}
    cands = [(r, abs(k), m * 10.0 ** k) for k in range(int(np.floor(np.log10(lo))) - 1,
                                                        int(np.ceil(np.log10(hi))) + 1) for m, r in rank.items()]
    cands = sorted(c for c in cands if lo * (1 - 1e-9) <= c[2] <= hi * (1 + 1e-9))
    gap = 0.95 * np.log10(hi / lo) / n
    ticks = []
    for _, _, v in cands:
        if all(abs(np.log10(v / t)) >= gap for t in ticks):
            ticks.append(v)
    return sorted(ticks)


def _nodal_on_grid(mesh, nodal, step_mm):
    """Bilinear interpolation of nodal values (n_nodes, k) on a pixel grid of ``step_mm`` over the mesh's bounding
    box: (k, n_axial, n_lateral) (NaN outside the mesh), spacing and origin."""
    from .fields import sample
    from .pixels import PointLocator

    p = np.asarray(mesh.p, float)
    x = np.arange(p[0].min(), p[0].max() + 1e-9, step_mm)
    y = np.arange(p[1].min(), p[1].max() + 1e-9, step_mm)
    X, Y = np.meshgrid(x, y, indexing="ij")
    loc = PointLocator(mesh).locate(np.column_stack([X.ravel(), Y.ravel()]))
    vals = np.asarray(nodal, float).reshape(p.shape[1], -1)
    out = np.full((vals.shape[1], X.size), np.nan)
    for k in range(vals.shape[1]):                 # a scalar field interpolated as the displacement is
        u = np.zeros(2 * p.shape[1])
        u[0::2] = vals[:, k]
        out[k, loc.inside] = sample(u, loc, fields=("ux",))["ux"]
    return out.reshape((vals.shape[1],) + X.shape), (step_mm, step_mm), (x[0], y[0])


def plot_inversion(result, out_png=None, *, dpi=100, figsize=None, title=None, at=None):
    """The relative shear-modulus image of :func:`femreg.invert`, its uncertainty when the result has one
    (``uncertainty``: per-element standard deviation of log mu), and the recovered axial strain (%) of the
    displacement it was computed from (:func:`femreg.fields.recovered_strains`, as in every femreg strain
    picture), on the inversion mesh.  ``result``: an :class:`femreg.inversion.InversionResult` (a file: read it
    with :func:`femreg.load_inversion`; ``InversionResult.plot`` is this function).  A result that did not
    converge gets the red failure banner.  Writes ``out_png`` if given; returns the figure.

    A 3D result (hexahedra) is drawn as three orthogonal slices through ``at`` (a point (x, y, z) mm, or
    "centre" (default), "stiffest", "softest"): :func:`femreg.volplot.plot_inversion_volume`; ``figsize`` does
    not apply there, and ``at`` does not apply to a 2D result."""
    from .fields import recovered_strains

    if not all(hasattr(result, k) for k in ("mesh", "mu", "strain_measured", "model", "beta")):
        raise InputError(f"plot_inversion needs an InversionResult (femreg.load_inversion reads a file), got "
                         f"{type(result).__name__}")
    if np.shape(result.mesh.p)[0] == 3:       # the result's own plot draws it with femreg.volplot (which
        if not callable(getattr(result, "plot", None)):   # builds on this module: no import of it from here)
            raise InputError("a 3D result is drawn by femreg.volplot.plot_inversion_volume")
        return result.plot(out_png, at=at, dpi=dpi, title=title)
    if at is not None:
        raise InputError("a slice position (at) applies to a 3D inversion only; this result is 2D")
    res = result
    plt = _mpl()
    p, t = res.mesh.p, res.mesh.t
    ext = (p[0].max() - p[0].min()) / max(p[1].max() - p[1].min(), 1e-12)
    unc = getattr(res, "uncertainty", None)
    unc = None if unc is None or np.size(unc) != t.shape[1] else np.asarray(unc, float)
    n = 3 if unc is not None else 2
    if figsize is None:
        figsize = (4.4 * n, min(max(3.0 * ext, 2.5), 8.0) + 1.2)
    fig, axes = plt.subplots(1, n, figsize=figsize, constrained_layout=True)
    plot_mesh_values(p, t, res.mu, ax=axes[0], log=True, cmap="viridis",
                     title="shear modulus $\\mu$", label="$\\mu$ / median (relative, -)")
    if unc is not None:
        blank = int(np.sum(~np.isfinite(unc)))              # NaN: elements the data do not constrain
        lo, hi = uncertainty_range(unc)
        plot_mesh_values(p, t, unc, ax=axes[1], cmap="magma", vmin=lo, vmax=hi,
                         title="uncertainty of $\\log\\mu$"
                         + ("\nNOT calibrated: tissue not piecewise uniform (see notes)"
                            if getattr(res, "uncertainty_calibrated", True) is False else "")
                         + (f"\n(grey = blank: {blank} of {unc.size} elements the data do not constrain)"
                            if blank else ""),
                         label=f"std of $\\log\\mu$ (-)\n{UNCERTAINTY_ENDS}")
        # the unconstrained elements (NaN, drawn transparent) on grey: white would read as magma's top, the
        # largest uncertainty
        axes[1].set_facecolor("0.6")
    h = float(np.min(np.ptp(p[:, t], axis=1)))                # smallest element extent, mm
    um = np.asarray(res.u_measured, float)
    if np.all(np.isfinite(um)) and np.any(um != 0):
        ns = recovered_strains(p, t, um)
        grid, sp, org = _nodal_on_grid(res.mesh, ns[:, 0], max(h / 8.0, 1e-3))
        plot_field(grid[0], sp, org, ax=axes[-1], title="recovered axial strain $\\varepsilon_{xx}$",
                   label="axial strain $\\varepsilon_{xx}$ (%)", scale=100.0)
    else:                                                   # no displacement stored: the element-mean strain
        cmap, lo, hi = colour_scale(100.0 * res.strain_measured[:, 0])
        plot_mesh_values(p, t, 100.0 * res.strain_measured[:, 0], ax=axes[-1], cmap=cmap, vmin=lo, vmax=hi,
                         title="element axial strain $\\varepsilon_{xx}$", label="axial strain $\\varepsilon_{xx}$ (%)")
    for ax in axes[1:]:
        ax.set_ylabel("")                                   # one depth axis label, at the left
    head = title or f"{res.model}, beta {res.beta:.3g}, {res.regularization.upper()}"
    if res.success:
        fig.suptitle(head)
    else:
        draw_failure(fig, inversion_banner(res, head), max_lines=6)
    fit_colorbars(fig, [list(axes)])
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def quality_pair(d) -> str:
    """The frames a result's quality map compares, from its saved fields ``d``: ``"frames I -> J"`` (``femreg
    register --pair``, ``femreg batch``), ``"frame K-1 -> K"`` (a track's accumulated frame K, whose quality is of
    its last increment), ``"frame 0 -> K"``; "" when the result does not say."""
    pair = np.ravel(d["pair"]) if d.get("pair") is not None else np.empty(0)
    if "frame" in d and "increment" in d:
        k = int(d["frame"])
        accumulated = str(d["mode"]) != "direct" if "mode" in d else True
        return f"frame {k - 1} -> {k}" if accumulated and k > 1 else f"frame 0 -> {k}"
    if pair.size == 2:
        return f"frames {int(pair[0])} -> {int(pair[1])}"
    return ""


def plot_quality(mesh_points, mesh_cells, quality, out_png=None, *, ax=None, threshold=0.5, dpi=100, pair=""):
    """Per-element quality map of a registration (NCC of reference and warped moving image over each element,
    :attr:`femreg.RegistrationResult.quality`) drawn on the mesh, mm axes; elements below ``threshold`` are
    outlined in black; ``pair`` (e.g. ``"frame 4 -> 5"``, :func:`quality_pair`) names the frames compared in the
    title.  Returns the Figure (saved to ``out_png`` when given)."""
    from matplotlib.collections import PolyCollection

    p = np.asarray(mesh_points, float)
    t = np.asarray(mesh_cells, np.int64)
    q = np.asarray(quality, float).ravel()
    if p.ndim != 2 or p.shape[0] != 2 or t.ndim != 2 or t.shape[0] != 4 or q.size != t.shape[1]:
        raise InputError(f"quality map needs (2, n) points, (4, n_el) quads and n_el values; got {p.shape}, "
                         f"{t.shape}, {q.size}")
    qmin = np.nanmin(q) if np.isfinite(q).any() else float("nan")
    bad = np.isfinite(q) & (q < threshold)
    ax = plot_mesh_values(p, t, q, ax=ax, title=f"registration quality{', ' + pair if pair else ''} "
                          f"(min {qmin:.2f})\noutlined: "
                          f"{int(bad.sum())} of {q.size} elements below {threshold:g}", vmin=0.0, vmax=1.0,
                          label="element NCC (reference vs warped moving)")
    if bad.any():
        polys = np.stack([p[1, t].T, p[0, t].T], axis=-1)          # (n_el, 4, [lateral, axial])
        ax.add_collection(PolyCollection(polys[bad], facecolors="none", edgecolors="k", linewidths=1.0))
    if out_png is not None:
        ax.figure.savefig(out_png, dpi=dpi)
    return ax.figure


def plot_shear(mesh_points, mesh_cells, shear, out_png=None, *, dpi=100, title=None):
    """The shear-strain product (:func:`femreg.shear.shear_strain_map`) on the mesh: e_xy per element (%), its
    predicted precision ``sigma`` relative to the image's median (logarithmic; the bound ranks elements by the
    lateral and axial information they hold, its constant is 30-80x loose, so no absolute value is drawn) and
    ``lateral_cells``, the element's width in lateral
    speckle cells; elements narrower than one (their du_y/dx rests on less than one speckle laterally) are
    outlined in the e_xy panel (unless every element is).  ``shear``: the dict of :func:`femreg.shear.shear_strain_map`.  Returns the
    Figure (saved to ``out_png`` when given)."""
    from matplotlib.collections import PolyCollection

    plt = _mpl()
    p = np.asarray(mesh_points, float)
    t = np.asarray(mesh_cells, np.int64)
    exy = 100.0 * np.asarray(shear["exy"], float).ravel()
    sigma = 100.0 * np.asarray(shear["sigma"], float).ravel()
    cells = np.asarray(shear["lateral_cells"], float).ravel()
    if not (exy.size == sigma.size == cells.size == t.shape[1]):
        raise InputError(f"shear map has {exy.size} values, the mesh {t.shape[1]} elements")
    extent = (np.ptp(p[1]), np.ptp(p[0]))
    w = 4.4 * min(max(extent[0] / max(extent[1], 1e-9), 0.5), 2.0)
    fig, axes = plt.subplots(1, 3, figsize=(3 * w + 1.5, 5.4), constrained_layout=True)
    finite = exy[np.isfinite(exy)]
    lim = float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0
    lim = lim if lim > 0 else 1.0
    from .shear import narrow_elements

    narrow = narrow_elements(shear)
    some = narrow.any() and not narrow.all()      # outlining every element would hide the image
    note = (f"\noutlined: {int(narrow.sum())} below 1 lateral cell" if some else
            "\nevery element below 1 lateral cell" if narrow.any() else "")
    ax = plot_mesh_values(p, t, exy, ax=axes[0], cmap=DIVERGING_CMAP, vmin=-lim, vmax=lim, label="e_xy (%)",
                          title="shear strain e_xy per element" + note)
    if some:
        polys = np.stack([p[1, t].T, p[0, t].T], axis=-1)
        ax.add_collection(PolyCollection(polys[narrow], facecolors="none", edgecolors="k", linewidths=0.8))
    ok = np.isfinite(sigma) & (sigma > 0)
    # relative to its median: the bound's constant is 30-80x loose (femreg.shear), so only the ranking is shown
    rel = np.where(ok, sigma / (np.median(sigma[ok]) if ok.any() else 1.0), np.nan)
    plot_mesh_values(p, t, rel, ax=axes[1], log=True, cmap=SEQUENTIAL_CMAP,
                     label="predicted sigma of e_xy / its median",
                     title="precision of e_xy, relative\n(higher: less certain)")
    cells = np.where(np.isfinite(cells), np.maximum(cells, 1e-3), np.nan)
    fin = cells[np.isfinite(cells)]
    c_lo, c_hi = (np.percentile(fin, [1, 99]) if fin.size else (0.5, 2.0))
    # the colours span at least 0.5-2 cells around the threshold 1: over the data's own range alone, element widths
    # of 5 and 6 lines (2.0 and 2.5 cells) alternated in full-scale stripes (a 15 MHz frame, 0.1 mm pitch)
    plot_mesh_values(p, t, cells, ax=axes[2], log=True, vmin=min(float(c_lo), CELLS_RANGE[0]),
                     vmax=max(float(c_hi), CELLS_RANGE[1]), cmap=SEQUENTIAL_CMAP,
                     label="element width / lateral speckle cell",
                     title="element width in lateral speckle\ncells (below 1: du_y/dx poorly measured)")
    if title:
        fig.suptitle(title, fontsize=10)
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig
