"""``femreg measure RESULT --inclusion X Y R``: contrast numbers of a registration or inversion result;
``--slide X0 X1``: the lateral slide across a sliding interface (:func:`measure_slide`).

A volume's result (``femreg register`` on RF volumes, or its ``femreg invert``): ``--inclusion X Y Z R`` is a
sphere and ``--background X0 X1 Y0 Y1 Z0 Z1`` a box; the same numbers over volumes instead of areas.

Elastogram (``OUT/elastogram.npz`` of ``femreg elastogram``): the same strain numbers over the pixels of its
normalised axial strain (the disk against the covered pixels outside it).

Registration result (``femreg register``): strain ratio SR, CNR_e and SNR_e of the axial strain
(:func:`femreg.metrics.contrast_metrics`) between the disk of radius R at (X, Y) and the background (the rest of
the mesh, or ``--background X0 X1 Y0 Y1`` less the disk).  Inversion result (``femreg invert``): the same strain
numbers from the displacement it was computed from, and the modulus contrast
(:func:`femreg.inversion.modulus_contrast`: elements wholly inside the disk against those wholly outside it and
inside the background; with a first-order uncertainty when the result carries ``uncertainty``).  Printed, and written
as JSON with ``--json FILE`` (``-o``).  Exit 0; 1 when the result is a failed one (the numbers are still given,
flagged); 2 on bad input (e.g. an inclusion outside the mesh: the message gives the mesh's bounds).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError


def add_parser(subparsers):
    p = subparsers.add_parser(
        "measure", help="strain ratio, CNR_e, SNR_e (and modulus contrast) of an inclusion in a result",
        description="Contrast numbers of a circular inclusion in a result .npz of `femreg register` (strain ratio "
                    "SR = background / inclusion mean axial strain, CNR_e, SNR_e of the background) or of "
                    "`femreg invert` (the same, and the modulus contrast inclusion / background); with --slide, "
                    "the lateral slide across a sliding interface.  Coordinates in "
                    "mm: x axial (depth), y lateral (a volume's result: z elevational, a spherical inclusion).")
    p.add_argument("result", help="result .npz of `femreg register`, `femreg track` or `femreg invert`, or the "
                                  "elastogram.npz of `femreg elastogram`")
    p.add_argument("--inclusion", type=float, nargs="+", metavar="MM",
                   help="X Y R: inclusion centre (axial X, lateral Y) and radius R, mm (a volume's result: "
                        "X Y Z R, a sphere)")
    p.add_argument("--slide", type=float, nargs=2, metavar=("X0", "X1"),
                   help="depths X0 < X1 (mm) on either side of a sliding interface (fascia, tendon sheath): the "
                        "lateral slide of the tissue at X1 against X0, median u_y along each depth over the mesh's "
                        "width (--lateral Y0 Y1 to limit it), with its spread; a 2D register or track result")
    p.add_argument("--lateral", type=float, nargs=2, metavar=("Y0", "Y1"),
                   help="with --slide: the lateral span (mm) the two depths are read over (default the mesh's)")
    p.add_argument("--background", type=float, nargs="+", metavar="MM",
                   help="X0 X1 Y0 Y1: background rectangle, mm (a volume's: X0 X1 Y0 Y1 Z0 Z1, a box), the "
                        "inclusion left out; default: the rest of the mesh")
    p.add_argument("--strain", choices=("element", "recovered"), default="element",
                   help="strain the region statistics use (default element: its region means follow from the "
                        "displacement on the region's boundary; recovered: the pictures' strain)")
    p.add_argument("--json", "-o", dest="json", metavar="FILE",
                   help="also write the numbers as JSON (missing folders are created)")
    p.set_defaults(func=run)
    return p


def _bounds(mesh):
    """(x0, x1, y0, y1[, z0, z1]) mm of the mesh."""
    p = np.asarray(mesh.p, float)
    return tuple(float(f(p[a])) for a in range(p.shape[0]) for f in (np.min, np.max))


def _bounds_text(b):
    return ", ".join(f"{a} {b[2 * k]:.2f} to {b[2 * k + 1]:.2f} mm" for k, a in enumerate("xyz"[:len(b) // 2]))


def _span_hint(covers, b, c) -> str:
    """A centre inside the bounds ``b`` but outside the region (a convex or sector fan, whose corners are not
    registered): where the region spans at the centre's lateral position ``c[1]``, in words."""
    xs = np.linspace(b[0], b[1], 401)
    inside = [x for x in xs if covers(np.array([x, c[1]]))]
    if not inside:
        return f"; it is not a rectangle (e.g. a convex or sector fan): nothing at y = {c[1]:g} mm"
    return (f"; it is not a rectangle (e.g. a convex or sector fan): at y = {c[1]:g} mm it spans x "
            f"{min(inside):.2f} to {max(inside):.2f} mm")


def _check_counts(dim, inclusion, background):
    """InputError unless --inclusion / --background have the counts of a ``dim``-D result."""
    kind = "a volume's result" if dim == 3 else "a 2D result"
    want = ("X Y Z R", 4, "X0 X1 Y0 Y1 Z0 Z1", 6) if dim == 3 else ("X Y R", 3, "X0 X1 Y0 Y1", 4)
    if len(inclusion) != want[1]:
        raise InputError(f"--inclusion takes {want[1]} numbers ({want[0]}, mm) for {kind}, got {len(inclusion)}: "
                         f"{' '.join(f'{v:g}' for v in inclusion)}")
    if background is not None and len(background) != want[3]:
        raise InputError(f"--background takes {want[3]} numbers ({want[2]}, mm) for {kind}, got "
                         f"{len(background)}: {' '.join(f'{v:g}' for v in background)}")


def _check_regions(mesh, inclusion, background):
    """InputError unless the inclusion's centre lies in the mesh and the background (if given) overlaps it."""
    dim = np.shape(mesh.p)[0]
    if dim == 3:
        from ..volume_fields import HexLocator

        def covers(c):
            return bool(HexLocator(mesh).locate(c[None])[0][0])
    else:
        from ..pixels import PointLocator

        def covers(c):
            return bool(PointLocator(mesh).locate(c[None]).inside[0])
    return _check_shapes(dim, _bounds(mesh), covers, inclusion, background, "the mesh")


def _check_shapes(dim, b, covers, inclusion, background, where):
    """InputError unless the inclusion's centre lies where ``covers(centre)`` and the background (if given)
    overlaps the bounds ``b`` (x0, x1, y0, y1[, z0, z1]) mm of the measured region, named ``where`` in messages;
    returns notes (an inclusion reaching beyond ``b``)."""
    _check_counts(dim, inclusion, background)
    c, r = np.asarray(inclusion[:-1], float), float(inclusion[-1])
    shape = "sphere" if dim == 3 else "disk"
    centre = ", ".join(f"{v:g}" for v in c)
    if not all(math.isfinite(v) for v in inclusion) or r <= 0:
        raise InputError(f"--inclusion needs a finite centre and a radius > 0 mm, got "
                         f"{' '.join(f'{v:g}' for v in inclusion)}")
    if not covers(c):
        # numbers copied from a MATLAB script in metres: a thousand times smaller, and inside once in mm
        metres = (covers(c * 1e3) and r * 1e3 < max(b[2 * a + 1] - b[2 * a] for a in range(dim)))
        hint = (f"; the numbers look like metres: pass them in mm, --inclusion "
                f"{' '.join(f'{v * 1e3:g}' for v in inclusion)}" if metres else "")
        if not hint and dim == 2 and b[0] <= c[0] <= b[1] and b[2] <= c[1] <= b[3]:
            hint = _span_hint(covers, b, c)
        raise InputError(f"inclusion centre ({centre}) mm lies outside {where} ({_bounds_text(b)}){hint}")
    notes = []
    if any(c[a] - r < b[2 * a] or c[a] + r > b[2 * a + 1] for a in range(dim)):
        # how much of it: a disk half off the edge (lateral positions counted from the first line, not the
        # centre) measures a different region from the one meant
        g = np.linspace(-1.0, 1.0, 41)
        pts = np.stack(np.meshgrid(*([g] * dim), indexing="ij"), -1).reshape(-1, dim)
        pts = c + r * pts[np.sum(pts ** 2, axis=1) <= 1.0]
        share = np.mean(np.all([(pts[:, a] >= b[2 * a]) & (pts[:, a] <= b[2 * a + 1]) for a in range(dim)], axis=0))
        notes.append(f"the inclusion {shape} extends beyond {where} ({_bounds_text(b)}); its part inside, "
                     f"{100 * share:.0f} % of it, is measured")
    if background is not None:
        lo, hi = np.asarray(background[0::2], float), np.asarray(background[1::2], float)
        text = " ".join(f"{v:g}" for v in background)
        if not all(math.isfinite(v) for v in background) or not np.all(lo < hi):
            names = " and ".join(f"{a.upper()}0 < {a.upper()}1" for a in "xyz"[:dim])
            raise InputError(f"--background needs {names} (mm), got {text}")
        if any(hi[a] <= b[2 * a] or lo[a] >= b[2 * a + 1] for a in range(dim)):
            raise InputError(f"--background {text} does not overlap {where} ({_bounds_text(b)})")
        if any(lo[a] < b[2 * a] or hi[a] > b[2 * a + 1] for a in range(dim)):   # as the inclusion's note
            notes.append(f"the background box extends beyond {where} ({_bounds_text(b)}); its part inside is "
                         "measured")
    return notes


def _small_inclusion_notes(mesh, inclusion) -> list:
    """A note when the inclusion is narrower than one element (median element size per axis): its element strain
    is then the strain of the one or two elements it touches, not a region's mean; with a hint when the numbers
    read in centimetres (ten times them lies inside the mesh, as a scanner's display gives depths in cm)."""
    p, t = np.asarray(mesh.p, float), np.asarray(mesh.t)
    dim = p.shape[0]
    corners = p[:, t]                                   # (dim, corners, elements)
    size = np.median(corners.max(axis=1) - corners.min(axis=1), axis=1)
    c, r = np.asarray(inclusion[:-1], float), float(inclusion[-1])
    if 2 * r >= float(np.min(size)):
        return []
    b = _bounds(mesh)
    shape = "sphere" if dim == 3 else "disk"
    note = (f"the inclusion {shape} ({2 * r:g} mm across) is narrower than one element "
            f"({' x '.join(f'{v:.2g}' for v in size)} mm): its numbers are those of the element(s) it touches, not "
            "of a region")
    inside = all(b[2 * a] <= 10 * c[a] <= b[2 * a + 1] for a in range(dim)) and 20 * r < max(
        b[2 * a + 1] - b[2 * a] for a in range(dim))
    if inside:
        note += f"; in centimetres? pass mm, --inclusion {' '.join(f'{10 * v:g}' for v in inclusion)}"
    return [note]


def _regions(inclusion, background):
    """(roi, background) callables on points (n, dim) mm: the disk / sphere and the box (None: everything)."""
    c, r = np.asarray(inclusion[:-1], float), float(inclusion[-1])

    def roi(p):
        return np.sum((np.asarray(p, float)[:, :c.size] - c) ** 2, axis=1) < r * r

    bg = None
    if background is not None:
        lo, hi = np.asarray(background[0::2], float), np.asarray(background[1::2], float)

        def bg(p):
            q = np.asarray(p, float)[:, :lo.size]
            return np.all((q >= lo) & (q <= hi), axis=1)
    return roi, bg


class _Displacement:
    """The mesh and nodal displacement of an inversion result, as :func:`contrast_metrics` reads them."""

    def __init__(self, mesh, u):
        self.mesh, self.u = mesh, u


class _Elements:
    """Some elements of an inversion result (``mesh``, ``mu``, ``centroids``), as
    :func:`femreg.inversion.modulus_contrast` reads them."""

    def __init__(self, res, keep):
        from skfem import MeshHex1, MeshQuad1

        mesh_type = MeshHex1 if np.shape(res.mesh.p)[0] == 3 else MeshQuad1
        self.mesh = mesh_type(np.asarray(res.mesh.p, float), np.ascontiguousarray(np.asarray(res.mesh.t)[:, keep]))
        self.mu = np.asarray(res.mu, float)[keep]
        self.centroids = self.mesh.p[:, self.mesh.t].mean(axis=1).T


def _modulus(res, roi, bg) -> dict:
    """:func:`femreg.inversion.modulus_contrast` over the inclusion and the background elements, and
    ``contrast_sd_log`` when ``res`` has ``uncertainty`` (per-element std of log mu): the standard deviation of
    log(contrast) to first order, elements taken independent (neighbours of a regularised inversion are
    correlated: a guide to the size, not a bound)."""
    from ..inversion import modulus_contrast

    node_in = np.asarray(roi(res.mesh.p.T), bool)[res.mesh.t]
    cin, cout = node_in.all(axis=0), (~node_in).all(axis=0)
    if bg is not None:
        cout &= np.asarray(bg(res.centroids), bool)
    sub = _Elements(res, cin | cout)
    out = {k: float(v) for k, v in modulus_contrast(sub, roi).items() if np.ndim(v) == 0}
    unc = getattr(res, "uncertainty", None)
    if unc is not None and np.size(unc) == res.mu.size:
        from skfem import Basis, ElementHex0, ElementQuad0

        e0 = ElementHex0() if np.shape(res.mesh.p)[0] == 3 else ElementQuad0()
        wmu = Basis(res.mesh, e0).dx.sum(axis=1) * np.asarray(res.mu, float)
        sig = np.asarray(unc, float).ravel()
        # d log(region mean) / d log mu_e = element e's share of the region's sum of area x mu
        var = sum(float(np.sum((wmu[s] / wmu[s].sum()) ** 2 * sig[s] ** 2)) for s in (cin, cout))
        out["contrast_sd_log"] = float(np.sqrt(var))
    return out


#: Keys of the elastogram file that `femreg elastogram` writes (OUT/elastogram.npz).
ELASTOGRAM_KEYS = ("exx", "ref_frame", "quality", "spacing", "origin")


def is_elastogram_file(path) -> bool:
    """True for the ``elastogram.npz`` of ``femreg elastogram`` (a normalised strain image, no displacement)."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            return all(k in z.files for k in ELASTOGRAM_KEYS) and "mesh_points" not in z.files
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, TypeError):   # TypeError: a .npy (one array)
        return False


class _Grid:
    """A strain image on the pixel grid, as :func:`contrast_metrics` reads a pixel-mask measurement."""

    def __init__(self, exx):
        self.exx = exx

    def on_grid(self, strain=None):
        return {"exx": self.exx}


def _measure_elastogram(path, inclusion, background) -> dict:
    """SR, CNR_e and SNR_e of an elastogram's normalised axial strain (pixels inside the disk against the covered
    pixels outside it, or inside ``background`` less the disk); strain ratios are scale-free, so the
    normalisation of each pair's strain by its mean leaves them as they are."""
    from ..metrics import contrast_metrics

    with np.load(path, allow_pickle=False) as z:
        exx = np.asarray(z["exx"], float)
        sp, org = np.asarray(z["spacing"], float), np.asarray(z["origin"], float)
    x = org[0] + sp[0] * np.arange(exx.shape[0])
    y = org[1] + sp[1] * np.arange(exx.shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    cov = np.isfinite(exx)
    if not cov.any():
        raise InputError(f"{path}: the elastogram covers no pixel")
    b = (float(X[cov].min()), float(X[cov].max()), float(Y[cov].min()), float(Y[cov].max()))

    def covers(c):      # the pixel nearest the centre, within the image, holds a strain
        i, j = int(np.argmin(np.abs(x - c[0]))), int(np.argmin(np.abs(y - c[1])))
        return bool(x[0] - sp[0] / 2 <= c[0] <= x[-1] + sp[0] / 2 and y[0] - sp[1] / 2 <= c[1] <= y[-1] + sp[1] / 2
                    and cov[i, j])

    notes = _check_shapes(2, b, covers, inclusion, background, "the elastogram's covered area")
    roi, bg = _regions(inclusion, background)
    P = np.column_stack([X.ravel(), Y.ravel()])
    try:
        vals = contrast_metrics(_Grid(exx), roi(P).reshape(exx.shape),
                                background=None if bg is None else bg(P).reshape(exx.shape))
    except ValueError as exc:
        raise InputError(f"{exc} (inclusion {inclusion}, covered area {_bounds_text(b)})") from None
    out = {"result": str(path), "kind": "elastogram", "success": True, "message": "", "flagged": False,
           "inclusion_mm": dict(zip(("x", "y", "r"), (float(v) for v in inclusion))),
           "background_mm": None if background is None else dict(zip(("x0", "x1", "y0", "y1"),
                                                                     (float(v) for v in background))),
           "strain": "normalised elastogram",
           "mesh_bounds_mm": dict(zip(("x0", "x1", "y0", "y1"), (round(v, 6) for v in b)))}
    out.update({k: float(v) for k, v in vals.items()})
    out["notes"] = notes
    return out


def measure(path, inclusion, background=None, strain="element") -> dict:
    """The numbers of ``femreg measure`` as a dict (JSON-ready); InputError on bad input.  ``path``: a result of
    ``femreg register`` / ``track`` / ``invert``, or the ``elastogram.npz`` of ``femreg elastogram`` (pixel
    statistics of its normalised strain; ``strain`` does not apply)."""
    from ..inversion import is_inversion_file, load_inversion
    from ..result import load_result
    from ..metrics import contrast_metrics

    if Path(path).is_file() and is_elastogram_file(path):
        return _measure_elastogram(path, inclusion, background)
    inversion = is_inversion_file(path)
    res = load_inversion(path) if inversion else load_result(path)
    small = _small_inclusion_notes(res.mesh, inclusion)
    notes = _check_regions(res.mesh, inclusion, background) + small
    roi, bg = _regions(inclusion, background)
    dim = np.shape(res.mesh.p)[0]
    box_keys = ("x0", "x1", "y0", "y1", "z0", "z1")[:2 * dim]
    out = {"result": str(path), "kind": "inversion" if inversion else "registration",
           "success": bool(res.success), "message": str(res.message), "flagged": not bool(res.success),
           "inclusion_mm": dict(zip(("x", "y", "z", "r") if dim == 3 else ("x", "y", "r"),
                                    (float(v) for v in inclusion))),
           "background_mm": None if background is None else dict(zip(box_keys, (float(v) for v in background))),
           "strain": strain, "mesh_bounds_mm": dict(zip(box_keys, (round(v, 6) for v in _bounds(res.mesh))))}
    source = _Displacement(res.mesh, res.u_measured) if inversion else res
    try:
        out.update({k: float(v) for k, v in contrast_metrics(source, roi, background=bg, strain=strain).items()})
        if inversion:
            out.update({f"modulus_{k}": v for k, v in _modulus(res, roi, bg).items()})
    except (ValueError, InputError) as exc:            # a region without samples: the regions, not the data, are wrong
        raise InputError(f"{exc} (inclusion {inclusion}, mesh {_bounds_text(_bounds(res.mesh))})"
                         + "".join(f"; {n}" for n in small)) from None
    out["notes"] = notes
    return out


def _report(m) -> str:
    inc = m["inclusion_mm"]
    centre = ", ".join(f"{inc[a]:g}" for a in "xyz" if a in inc)
    bg = m["background_mm"]
    lines = [f"{m['kind']} result {m['result']}",
             f"inclusion: {'sphere' if 'z' in inc else 'disk'}, centre ({centre}) mm, radius {inc['r']:g} mm; "
             "background: " + (("rest of the covered pixels" if m["kind"] == "elastogram" else "rest of the mesh")
                               if bg is None else
                               ", ".join(f"{a} {bg[a + '0']:g}-{bg[a + '1']:g}" for a in "xyz" if a + "0" in bg)
                               + " mm"),
             f"strain ratio SR (background / inclusion, {m['strain']} strain): {m['SR']:.4g}",
             f"CNR_e: {m['CNR_e']:.4g} ({10 * math.log10(m['CNR_e']) if m['CNR_e'] > 0 else float('-inf'):.1f} dB)",
             f"SNR_e (background): {m['SNR_e']:.4g}"]
    if "modulus_contrast" in m:
        s = f"modulus contrast (inclusion / background): {m['modulus_contrast']:.4g}"
        if "modulus_contrast_sd_log" in m:
            sd = m["modulus_contrast_sd_log"]
            s += (f" (x/ {math.exp(sd):.3g} at one standard deviation: "
                  f"{m['modulus_contrast'] * math.exp(-sd):.3g}-{m['modulus_contrast'] * math.exp(sd):.3g})"
                  if math.isfinite(sd) else
                  " (spread unknown: the data do not constrain some of the elements measured)")
        lines.append(s)
        if "modulus_cv_background" in m:
            lines.append(f"background modulus CV: {100 * m['modulus_cv_background']:.3g} %")
        lines.append(f"for comparison, the strain ratio read as a modulus contrast: {m['SR']:.4g}")
    lines += [f"note: {n}" for n in m["notes"]]
    if m["flagged"]:
        state = "flagged" if str(m["message"]).startswith("FLAGGED") else "failed"   # say it once, as the result does
        reason = str(m["message"]).removeprefix("FAILED: ").removeprefix("FLAGGED: ")
        verb = "is flagged" if state == "flagged" else "failed"
        lines.append(f"FLAGGED: the {m['kind']} {verb} ({reason}); these numbers describe a {state} result")
    return "\n".join(lines)


#: Rows of points along each depth of ``--slide`` (per mm of width; at least 16 points).
SLIDE_POINTS_PER_MM = 10


def measure_slide(path, depths, lateral=None) -> dict:
    """The lateral slide across an interface of a 2D registration result (``femreg register`` / ``track``): the
    median lateral displacement u_y (mm) along depth ``depths[1]`` minus that along ``depths[0]`` over the mesh's
    width (or ``lateral`` = (y0, y1) mm), and the interquartile range of the difference point by point (the slide's
    spread along the width).  InputError on bad input (depths not increasing, outside the mesh, no 2D result)."""
    from ..inversion import is_inversion_file
    from ..result import load_result

    x0, x1 = (float(v) for v in depths)
    if not x0 < x1:
        raise InputError(f"--slide X0 X1 takes two increasing depths (mm) on either side of the interface, got "
                         f"{x0:g} {x1:g}")
    if (Path(path).is_file() and is_elastogram_file(path)) or is_inversion_file(path):
        raise InputError(f"{path}: --slide reads the lateral displacement of a `femreg register` or `femreg track` "
                         "result; this file holds none")
    res = load_result(path)
    if np.shape(res.mesh.p)[0] != 2:
        raise InputError(f"{path}: --slide measures 2D results; this one is a volume's")
    b = _bounds(res.mesh)
    y0, y1 = (b[2], b[3]) if lateral is None else (float(lateral[0]), float(lateral[1]))
    for x in (x0, x1):
        if not b[0] <= x <= b[1]:
            raise InputError(f"--slide depth {x:g} mm lies outside the mesh ({_bounds_text(b)})")
    if not (y0 < y1 and b[2] <= y0 and y1 <= b[3]):
        raise InputError(f"--lateral {y0:g} {y1:g} must be an increasing span inside the mesh ({_bounds_text(b)})")
    y = np.linspace(y0, y1, max(16, int(SLIDE_POINTS_PER_MM * (y1 - y0)) + 1))
    u0 = res.displacement(np.column_stack([np.full_like(y, x0), y]))[:, 1]
    u1 = res.displacement(np.column_stack([np.full_like(y, x1), y]))[:, 1]
    ok = np.isfinite(u0) & np.isfinite(u1)
    if ok.sum() < 2:
        raise InputError(f"--slide: the depths {x0:g} and {x1:g} mm hold no displacement over {y0:g}-{y1:g} mm")
    d = u1[ok] - u0[ok]
    q1, q3 = np.percentile(d, [25, 75])
    return {"depths_mm": [x0, x1], "lateral_mm": [float(y0), float(y1)],
            "slide_mm": float(np.median(u1[ok]) - np.median(u0[ok])), "slide_iqr_mm": float(q3 - q1),
            "uy_shallow_mm": float(np.median(u0[ok])), "uy_deep_mm": float(np.median(u1[ok])),
            "success": bool(res.success), "message": str(res.message)}


def _slide_report(s) -> str:
    x0, x1 = s["depths_mm"]
    return (f"slide (lateral u_y at {x1:g} mm minus at {x0:g} mm, median over y {s['lateral_mm'][0]:.3g}-"
            f"{s['lateral_mm'][1]:.3g} mm): {1e3 * s['slide_mm']:.4g} um (interquartile range along the width "
            f"{1e3 * s['slide_iqr_mm']:.3g} um; u_y {1e3 * s['uy_shallow_mm']:.4g} / {1e3 * s['uy_deep_mm']:.4g} um)")


def run(args) -> int:
    out = Path(args.json) if args.json else None
    if out is not None and out.suffix.lower() != ".json":
        raise InputError(f"--json must name a .json file, got {out}")
    if args.inclusion is None and args.slide is None:
        raise InputError("pass --inclusion X Y R (strain ratio, CNR_e) or --slide X0 X1 (the slide across an "
                         "interface), or both")
    if args.lateral is not None and args.slide is None:
        raise InputError("--lateral qualifies --slide: pass --slide X0 X1 with it")
    slide = None if args.slide is None else measure_slide(args.result, args.slide, args.lateral)
    if args.inclusion is None:
        m = {"result": str(args.result), "kind": "registration", "flagged": not slide["success"],
             "message": slide["message"], "slide": slide}
        print(f"registration result {args.result}\n{_slide_report(slide)}")
    else:
        m = measure(args.result, tuple(args.inclusion),
                    None if args.background is None else tuple(args.background), args.strain)
        if slide is not None:
            m["slide"] = slide
        print(_report(m) + ("" if slide is None else "\n" + _slide_report(slide)))
    if out is not None:
        from .._atomic import atomic_write_text

        atomic_write_text(out, json.dumps(m, indent=2, default=float) + "\n")
        print(f"wrote {out}")
    if m["flagged"]:
        state = "flagged" if str(m["message"]).startswith("FLAGGED") else "failed"
        reason = str(m["message"]).removeprefix("FAILED: ").removeprefix("FLAGGED: ")
        print(f"femreg measure: the result is a {state} {m['kind']}: {reason}", file=sys.stderr)
        return 1
    return 0
