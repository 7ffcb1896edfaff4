"""``femreg measure RESULT --inclusion X Y R``: contrast numbers of a registration or inversion result.

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
                    "`femreg invert` (the same, and the modulus contrast inclusion / background).  Coordinates in "
                    "mm: x axial (depth), y lateral.  Exit 0; 1 for a failed result (numbers flagged); 2 on bad "
                    "input.")
    p.add_argument("result", help="result .npz of `femreg register` or `femreg invert`")
    p.add_argument("--inclusion", required=True, type=float, nargs=3, metavar=("X", "Y", "R"),
                   help="inclusion centre (axial X, lateral Y) and radius R, mm")
    p.add_argument("--background", type=float, nargs=4, metavar=("X0", "X1", "Y0", "Y1"),
                   help="background rectangle, mm (the disk left out); default: the rest of the mesh")
    p.add_argument("--strain", choices=("element", "recovered"), default="element",
                   help="strain the region statistics use (default element: its region means follow from the "
                        "displacement on the region's boundary; recovered: the pictures' strain)")
    p.add_argument("--json", "-o", dest="json", metavar="FILE", help="also write the numbers as JSON")
    p.set_defaults(func=run)
    return p


def _bounds(mesh):
    p = np.asarray(mesh.p, float)
    return float(p[0].min()), float(p[0].max()), float(p[1].min()), float(p[1].max())


def _bounds_text(b):
    return f"x {b[0]:.2f} to {b[1]:.2f} mm, y {b[2]:.2f} to {b[3]:.2f} mm"


def _check_regions(mesh, inclusion, background):
    """InputError unless the inclusion's centre lies in the mesh and the background (if given) overlaps it."""
    from ..pixels import PointLocator

    x, y, r = inclusion
    b = _bounds(mesh)
    if not all(math.isfinite(v) for v in inclusion) or r <= 0:
        raise InputError(f"--inclusion needs a finite centre and a radius > 0 mm, got {x:g} {y:g} {r:g}")
    if not PointLocator(mesh).locate(np.array([[x, y]])).inside[0]:
        raise InputError(f"inclusion centre ({x:g}, {y:g}) mm lies outside the mesh ({_bounds_text(b)})")
    notes = []
    if x - r < b[0] or x + r > b[1] or y - r < b[2] or y + r > b[3]:
        notes.append("the inclusion disk extends beyond the mesh; its part inside is measured")
    if background is not None:
        x0, x1, y0, y1 = background
        if not (x0 < x1 and y0 < y1) or not all(math.isfinite(v) for v in background):
            raise InputError(f"--background needs X0 < X1 and Y0 < Y1 (mm), got {x0:g} {x1:g} {y0:g} {y1:g}")
        if x1 <= b[0] or x0 >= b[1] or y1 <= b[2] or y0 >= b[3]:
            raise InputError(f"--background {x0:g} {x1:g} {y0:g} {y1:g} does not overlap the mesh "
                             f"({_bounds_text(b)})")
    return notes


def _regions(inclusion, background):
    x, y, r = inclusion

    def roi(p):
        return (p[:, 0] - x) ** 2 + (p[:, 1] - y) ** 2 < r * r

    bg = None
    if background is not None:
        x0, x1, y0, y1 = background

        def bg(p):
            return (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
    return roi, bg


class _Displacement:
    """The mesh and nodal displacement of an inversion result, as :func:`contrast_metrics` reads them."""

    def __init__(self, mesh, u):
        self.mesh, self.u = mesh, u


class _Elements:
    """Some elements of an inversion result (``mesh``, ``mu``, ``centroids``), as
    :func:`femreg.inversion.modulus_contrast` reads them."""

    def __init__(self, res, keep):
        from skfem import MeshQuad1

        self.mesh = MeshQuad1(np.asarray(res.mesh.p, float), np.asarray(res.mesh.t)[:, keep])
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
        from skfem import Basis, ElementQuad0

        wmu = Basis(res.mesh, ElementQuad0()).dx.sum(axis=1) * np.asarray(res.mu, float)
        sig = np.asarray(unc, float).ravel()
        # d log(region mean) / d log mu_e = element e's share of the region's sum of area x mu
        var = sum(float(np.sum((wmu[s] / wmu[s].sum()) ** 2 * sig[s] ** 2)) for s in (cin, cout))
        out["contrast_sd_log"] = float(np.sqrt(var))
    return out


def measure(path, inclusion, background=None, strain="element") -> dict:
    """The numbers of ``femreg measure`` as a dict (JSON-ready); InputError on bad input."""
    from ..inversion import is_inversion_file, load_inversion
    from ..result import load_result
    from ..metrics import contrast_metrics

    inversion = is_inversion_file(path)
    res = load_inversion(path) if inversion else load_result(path)
    notes = _check_regions(res.mesh, inclusion, background)
    roi, bg = _regions(inclusion, background)
    out = {"result": str(path), "kind": "inversion" if inversion else "registration",
           "success": bool(res.success), "message": str(res.message), "flagged": not bool(res.success),
           "inclusion_mm": dict(zip(("x", "y", "r"), (float(v) for v in inclusion))),
           "background_mm": None if background is None else dict(zip(("x0", "x1", "y0", "y1"),
                                                                     (float(v) for v in background))),
           "strain": strain, "mesh_bounds_mm": dict(zip(("x0", "x1", "y0", "y1"), _bounds(res.mesh)))}
    source = _Displacement(res.mesh, res.u_measured) if inversion else res
    try:
        out.update({k: float(v) for k, v in contrast_metrics(source, roi, background=bg, strain=strain).items()})
        if inversion:
            out.update({f"modulus_{k}": v for k, v in _modulus(res, roi, bg).items()})
    except (ValueError, InputError) as exc:            # a region without samples: the regions, not the data, are wrong
        raise InputError(f"{exc} (inclusion {inclusion}, mesh {_bounds_text(_bounds(res.mesh))})") from None
    out["notes"] = notes
    return out


def _report(m) -> str:
    inc = m["inclusion_mm"]
    lines = [f"{m['kind']} result {m['result']}",
             f"inclusion: centre ({inc['x']:g}, {inc['y']:g}) mm, radius {inc['r']:g} mm; background: "
             + ("rest of the mesh" if m["background_mm"] is None else
                "x {x0:g}-{x1:g}, y {y0:g}-{y1:g} mm".format(**m["background_mm"])),
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


def run(args) -> int:
    out = Path(args.json) if args.json else None
    if out is not None and out.suffix.lower() != ".json":
        raise InputError(f"--json must name a .json file, got {out}")
    m = measure(args.result, tuple(args.inclusion), None if args.background is None else tuple(args.background),
                args.strain)
    print(_report(m))
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
