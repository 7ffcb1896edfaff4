"""3D against 2D registration on the paper's 3D phantom imaged as RF volumes.

The paper's 3D FE model (HI by default: the 4x stiffer 15 mm sphere, 30 mm deep) imaged as volumes covering its
imaged plane (72 mm deep x 44 mm lateral) and +-10 mm elevationally (``forward.volume.paper_volume_sequence``:
the paper's 5.5 MHz PSF and 40 MHz / 0.3 mm sampling, a 2 mm elevational beam on 0.5 mm planes, 12 dB SNR,
cached), frames 1 -> 7 of its compression schedule (0.8 % mean axial strain).

* 2D: ``femreg.register`` on the central plane (z = 0) of both volumes, as the paper registers its 2D frames.
* 3D: ``femreg.register`` on the volumes with ``spacing=(dx, dy, dz)``, where the installed femreg registers
  volumes (otherwise the script says so).

Errors against the exact FE truth (``forward.volume.FEVolumeField``), with femreg.metrics' formulas so that the
numbers compare with docs/study_report.md: on the central plane, integrated with the 2D registration mesh's
quadrature (the same domain and weights for both), relative L2 errors of u_x, u_y and of the in-plane strains and
the in-plane total strain (e_xy counted twice); for 3D also u_z and the six-component total strain over the
interior of the volume (2 mm margin), which 2D cannot measure.

Inversions (unless ``--no-inversion``), over the sphere's box of benchmarks/inversion3d.py clipped to the volume's
interior: 3D ``femreg.invert`` (hexahedra, 2 mm, beta 1e-3) of the registered and of the exact 3D displacement,
2D plane-stress ``femreg.invert`` (beta rule) of the 2D registration and of the exact in-plane displacement;
contrast :func:`femreg.inversion.modulus_contrast` and the 0.7 R / 1.6-2.5 R ring contrast of
benchmarks/inversion.py on the central plane (true 4).

Run: ``python benchmarks/volume_study.py [--inclusion HI] [--crop X0 X1 Y0 Y1 Z0 Z1] [--quick] [--element-size H]
[--alpha-3d A] [--json FILE]``.  ``--quick`` crops to 20-42 mm deep, +-11 mm lateral and +-5 mm elevational around the inclusion
(the crop also applies to the 2D plane).  The first run renders and caches the volumes (minutes; about 1.8 M
scatterers).  The report section: ``python benchmarks/volume_study.py --section paperstudy/volume_section.md
RUN.json [RUN.json ...] --into docs/study_report.md`` (``femreg study`` carries paperstudy/volume_section.md into
the report it writes); the records of the runs in the report: paperstudy/volume_runs/ (full, plane5 = +-5 mm,
quick, quick_h1 = 1 mm, quick_h112 = 1 x 1 x 2 mm elements, full_refine / quick_refine = ``--refine auto``; the
others predate the volume refinement and are unrefined), the findings lines: ``--notes paperstudy/volume_runs/notes.txt``.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import femreg  # noqa: E402
from femreg import metrics as M  # noqa: E402
from femreg.errors import InputError  # noqa: E402
from forward.volume import STRAIN_COMPONENTS_3D, paper_volume_sequence  # noqa: E402

IN_PLANE = [0, 1, 3]          # exx, eyy, exy of the six 3D components
#: The inclusion of the paper's 3D model: centre (x, y, z) mm, radius mm.
CENTRE, RADIUS = (30.0, 0.0, 0.0), 7.5
#: The inversion region of benchmarks/inversion3d.py (``sphere``), clipped to the registered volume's interior.
INV_REGION = (15.0, 45.0, -15.0, 15.0, -10.0, 10.0)
#: 3D inversion: element size mm and fixed beta of benchmarks/inversion3d.py (exact HI displacement: 4.14).
INV_H_3D, INV_BETA_3D = 2.0, 1e-3


def crop(seq, box):
    """Voxel slices and origin of ``box`` = (x0, x1, y0, y1, z0, z1) mm (None: everything)."""
    g = seq.grid
    if box is None:
        return (slice(None),) * 3, g.origin
    sl = []
    for a in range(3):
        c = g.axis(a)
        idx = np.flatnonzero((c >= box[2 * a] - 1e-9) & (c <= box[2 * a + 1] + 1e-9))
        if idx.size < 4:
            raise InputError(f"crop {box} leaves {idx.size} samples along axis {a}")
        sl.append(slice(int(idx[0]), int(idx[-1]) + 1))
    return tuple(sl), tuple(float(g.axis(a)[s.start]) for a, s in enumerate(sl))


def plane_truth(field):
    """In-plane true displacement and strain callables (n, 2) -> (n, 2), (n, 3) at z = 0."""
    def p3(p):
        p = np.asarray(p, float)
        return np.column_stack([p, np.zeros(len(p))])

    return (lambda p: field.displacement(p3(p))[:, :2]), (lambda p: field.strain(p3(p))[:, IN_PLANE])


def plane_errors_3d(res3, res2, field) -> dict:
    """femreg.metrics' relative errors of the 3D result on the central plane, at the 2D mesh's quadrature points."""
    pts, w, _ = M.mesh_quadrature(res2.mesh)
    q = np.column_stack([pts, np.zeros(len(pts))])
    um, em = np.asarray(res3.displacement(q), float), np.asarray(res3.strain(q), float)
    ok = np.all(np.isfinite(um), axis=1) & np.all(np.isfinite(em), axis=1)
    ut, et = field.displacement(q), field.strain(q)
    err = M._relative_errors(w[ok], um[ok, :2], ut[ok, :2], em[ok][:, IN_PLANE], et[ok][:, IN_PLANE])
    return {k: 100.0 * v for k, v in err.items()}


def volume_errors_3d(res3, seq, k, sl, origin, margin_mm=2.0, chunk=1 << 18) -> dict:
    """u_z and the six-component total strain (shear twice) over the interior voxels, relative L2 in %; summed
    over axial slabs of about ``chunk`` voxels (the full volume's 22 M voxels at once took ~15 GB)."""
    g = seq.grid
    axes = [g.axis(a)[s] for a, s in enumerate(sl)]
    x, y, z = (c[(c >= c[0] + margin_mm) & (c <= c[-1] - margin_mm)] for c in axes)
    wt = np.array([1, 1, 1, 2, 2, 2], float)
    sums = np.zeros(4)                   # |uz - uz_t|^2, |uz_t|^2, weighted |e - e_t|^2, weighted |e_t|^2
    n_ok = 0
    step = max(1, chunk // (y.size * z.size))
    for i0 in range(0, x.size, step):
        X, Y, Z = np.meshgrid(x[i0:i0 + step], y, z, indexing="ij")
        P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
        uz = np.asarray(res3.displacement(P), float)[:, 2]
        em = np.asarray(res3.strain(P), float)
        ut, et = seq.true_displacement(k, P), seq.true_strain(k, P)
        ok = np.isfinite(uz) & np.all(np.isfinite(em), axis=1)
        sums += [np.sum((uz[ok] - ut[ok, 2]) ** 2), np.sum(ut[ok, 2] ** 2),
                 np.sum(wt * (em[ok] - et[ok]) ** 2), np.sum(wt * et[ok] ** 2)]
        n_ok += int(ok.sum())
    return {"uz": 100.0 * float(np.sqrt(sums[0] / sums[1])), "e6": 100.0 * float(np.sqrt(sums[2] / sums[3])),
            "interior_voxels": n_ok}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (monotone: it includes the loaded volumes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def in_sphere(points):
    p = np.asarray(points, float)
    c = np.asarray(CENTRE[:p.shape[1]])
    return np.sum((p - c) ** 2, axis=1) < RADIUS ** 2


def sampled_contrast(inv, dim):
    """Mean relative mu inside 0.7 R over the mean in the ring 1.6-2.5 R on the central plane (points every
    0.25 mm, as benchmarks/inversion.py), or None where the ring has fewer than half its points in the mesh."""
    g = np.arange(-2.5 * RADIUS, 2.5 * RADIUS + 1e-9, 0.25)
    X, Y = np.meshgrid(g, g, indexing="ij")
    r = np.hypot(X, Y).ravel()
    pts = np.column_stack([X.ravel() + CENTRE[0], Y.ravel() + CENTRE[1]] + ([np.zeros(r.size)] if dim == 3 else []))
    v = inv.shear_modulus(pts)
    ring_all = (r > 1.6 * RADIUS) & (r < 2.5 * RADIUS)
    inner, ring = (r < 0.7 * RADIUS) & np.isfinite(v), ring_all & np.isfinite(v)
    if ring.sum() < 0.5 * ring_all.sum() or not inner.any():
        return None
    return float(np.mean(v[inner]) / np.mean(v[ring]))


def inversion_row(inv, dim, seconds) -> dict:
    """femreg.inversion.modulus_contrast (elements fully inside / fully outside the sphere) and the sampled
    0.7 R / ring contrast of an inversion."""
    from femreg.inversion import modulus_contrast

    m = modulus_contrast(inv, in_sphere)
    return {"contrast": m["contrast"], "cv_background": m["cv_background"], "ring_contrast": sampled_contrast(inv, dim),
            "beta": float(inv.beta), "elements": int(inv.mu.size), "success": bool(inv.success),
            "weights": [float(x) for x in inv.weights],
            "boundary": "fitted" if "boundary values fitted" in inv.model_rule else "measured",
            "model": str(inv.model), "time_s": seconds}


def inversion_region(seq, sl, margin_mm=2.0):
    """INV_REGION clipped to the cropped volume less ``margin_mm`` (the registration's interior)."""
    g = seq.grid
    out = []
    for a in range(3):
        c = g.axis(a)[sl[a]]
        out += [max(INV_REGION[2 * a], c[0] + margin_mm), min(INV_REGION[2 * a + 1], c[-1] - margin_mm)]
    return tuple(float(v) for v in out)


def inversions(res2, res3, field, region) -> dict:
    """The 2D plane-stress inversion (femreg's beta rule) of the 2D registration and of the exact plane
    displacement, and the 3D inversion (hexahedra, INV_H_3D, INV_BETA_3D) of the 3D registration, of the exact
    3D displacement and of the registered in-plane components with the exact u_z (which component limits), all
    over ``region`` (its in-plane part for 2D)."""
    out = {}
    tu, _ = plane_truth(field)
    reg2 = ((region[0], region[1]), (region[2], region[3]))
    for name, disp, kw in (("2d_registered", res2, {}), ("2d_exact", tu, {})):
        t = time.perf_counter()
        inv = femreg.invert(disp, model="plane-stress", region=reg2, uncertainty=False, **kw)
        out[name] = inversion_row(inv, 2, time.perf_counter() - t)
    if res3 is not None:
        def exact_uz(pts):  # the registered in-plane components with the exact elevational one
            return np.column_stack([np.asarray(res3.displacement(pts), float)[:, :2], field.displacement(pts)[:, 2]])

        for name, disp in (("3d_registered", res3), ("3d_exact", field.displacement),
                           ("3d_registered_exact_uz", exact_uz)):
            t = time.perf_counter()
            inv = femreg.invert(disp, model="3d", region=region, element_size=INV_H_3D, beta=INV_BETA_3D,
                                uncertainty=False)
            out[name] = inversion_row(inv, 3, time.perf_counter() - t)
    for k, v in out.items():
        ring = f"{v['ring_contrast']:.2f}" if v["ring_contrast"] is not None else "-"
        print(f"inversion {k:14s}: contrast {v['contrast']:.2f} (true 4), ring {ring}, CV bg "
              f"{100 * v['cv_background']:.1f} %, beta {v['beta']:.3g}, {v['elements']} elements, "
              f"{v['time_s']:.1f} s, success {v['success']}", flush=True)
    return out


BEGIN, END = "<!-- volume-study: begin (benchmarks/volume_study.py --section) -->", "<!-- volume-study: end -->"
#: The targets: in-plane total strain error on the central plane (%), and the 3D contrast's distance to 4.
TARGET_E, TARGET_CONTRAST = 6.0, 0.25


def _extent(r) -> str:
    b, h = r.get("extent_mm") or r["crop_mm"], r.get("element_size_mm")
    e = "full volume" if r["crop_mm"] is None else "crop"
    if b is not None:
        e += f" {b[0]:.0f}-{b[1]:.0f} x {b[2]:.0f}..{b[3]:.0f} x {b[4]:.0f}..{b[5]:.0f} mm"
    h = [2.0] if h is None else (h if isinstance(h, list) else [h])
    e += f", {' x '.join(f'{v:g}' for v in (h if len(set(h)) > 1 else h[:1]))} mm elements"
    e += f", 3D alpha {r['alpha_3d']:g}" if r.get("alpha_3d") is not None else ""
    return e + (f", 3D refine={r['refine']}" if r.get("refine") not in (None, "off") else "")


def section(runs: list, notes=()) -> list:
    """Markdown lines of the report section from the JSON records of :func:`main` (one per extent)."""
    f = lambda v, d=2: "-" if v is None else f"{v:.{d}f}"  # noqa: E731
    L = [BEGIN, "", "## 3D against 2D on the paper's 3D phantom", "",
         "The paper's 3D FE model (HI: the 4x stiffer 15 mm sphere at 30 mm depth) imaged as RF volumes "
         "(`forward.volume.paper_volume_sequence`: the paper's 5.5 MHz PSF and 40 MHz sampling, 0.3 mm lateral "
         "lines, a 2 mm elevational beam on 0.5 mm planes, 12 dB SNR, seed 0) over the paper's imaged plane "
         "(72 mm deep x 44 mm lateral) and +-10 mm elevationally, frames 1 -> 7 (0.8 % mean axial strain).  2D: "
         "`femreg.register` on the central plane z = 0 of both volumes; 3D: `femreg.register` on the volumes "
         "(trilinear hexahedra), both with `momentum-stress` (R_P_sigma) and femreg's defaults (2 mm hexahedra unless "
         "the column says otherwise; alpha rescaled with the element size by femreg; in 2D, where no element size was "
         "given (the 2 mm columns), femreg's default mesh of the plane, at most 1.5 mm for R_P_sigma, refined by "
         "default).  "
         "Errors against the exact FE truth (relative L2, %, shear counted twice): the in-plane ones on the "
         "central plane at the 2D mesh's quadrature points (the same points and weights for both); u_z and the "
         "six-component strain over the volume's interior (2 mm margin), which 2D cannot give.  Times: the whole "
         "`register` call, wall and CPU, on the shared 2-core machine; memory: the process' peak RSS after the "
         "registration (it includes both volumes, float64).  `python benchmarks/volume_study.py [--quick]`.", ""]
    head = "| quantity |" + "".join(f" 2D, {_extent(r)} | 3D, {_extent(r)} |" for r in runs)
    L += [head, "|---|" + "---|---|" * len(runs)]
    for label, key in (("u_x %", "ux"), ("u_y %", "uy"), ("u_z %", "uz"), ("e_xx %", "exx"), ("e_yy %", "eyy"),
                       ("e_xy %", "exy"), ("**in-plane total strain %** (central plane)", "e"),
                       ("mesh floor of the in-plane total strain % (truth at the mesh's nodes)", "floor_e"),
                       ("six-component total strain % (volume interior)", "e6")):
        L.append(f"| {label} |" + "".join(f" {f(r['2d'].get(key))} | {f((r.get('3d') or {}).get(key))} |"
                                            for r in runs))
    for label, key, d in (("wall s", "time_s", 1), ("CPU s", "cpu_s", 1), ("peak RSS MB", "peak_rss_mb", 0)):
        L.append(f"| {label} |" + "".join(f" {f(r['2d'].get(key), d)} | {f((r.get('3d') or {}).get(key), d)} |"
                                            for r in runs))
    L.append("| voxels (axial x lateral x elevational) |" + "".join(
        f" {r['shape'][0]} x {r['shape'][1]} (plane) | {' x '.join(map(str, r['shape']))} |" for r in runs))
    L += ["", "Modulus inversion over the sphere's box of `benchmarks/inversion3d.py` (x 15-45, y +-15, z +-10 mm) "
          "clipped to the registered volume less 2 mm: 3D `femreg.invert` (hexahedra 2 mm, beta 1e-3 fixed, "
          "nearly incompressible, femreg's defaults at the time of the run: misfit weights and boundary in the "
          "table; runs without them used 1 / 0.1 / 0.1 and the measured boundary) of the registered and of the "
          "exact 3D displacement; 2D plane-stress `femreg.invert` (beta by femreg's rule) of the 2D registration and of the "
          "exact in-plane displacement on the central plane.  Contrast: `femreg.inversion.modulus_contrast` (mean "
          "mu of the elements fully inside the sphere over those fully outside; true 4); ring: mean mu inside 0.7 R "
          "over the ring 1.6-2.5 R on the central plane (`benchmarks/inversion.py`; '-' where the region does not "
          "hold the ring).", "",
          "| extent | inversion region mm | displacement | model | contrast (true 4) | ring contrast | CV bg % | "
          "beta | weights, boundary | elements | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    names = (("3d_registered", "3D registration", "3D"), ("3d_exact", "exact 3D", "3D"),
             ("3d_registered_exact_uz", "3D registration, exact u_z", "3D"),
             ("2d_registered", "2D registration", "plane stress"), ("2d_exact", "exact in-plane", "plane stress"))
    for r in runs:
        inv = r.get("inversion") or {}
        reg = " x ".join(f"{a:.0f}..{b:.0f}" for a, b in zip(r["inversion_region_mm"][::2],
                                                         r["inversion_region_mm"][1::2])) if inv else "-"
        for key, what, model in names:
            v = inv.get(key)
            if v is None:
                continue
            wts = v.get("weights") or ([1.0, 0.1, 0.1] if model == "3D" else [1.0, 0.1])
            L.append(f"| {_extent(r)} | {reg} | {what} | {model} | {v['contrast']:.2f}{'' if v['success'] else '*'}"
                     f" | {f(v['ring_contrast'])} | {100 * v['cv_background']:.1f} | {v['beta']:.3g} | "
                     f"{' / '.join(f'{x:.3g}' for x in wts)}, {v.get('boundary', 'measured')} | "
                     f"{v['elements']} | {v['time_s']:.1f} |")
    L += ["| (reference) | 15..45 x -15..15 x -10..10 | exact 3D | 3D | 4.14 | - | - | 0.001 | 1 / 0.1 / 0.01, "
          "fitted | - | - |", "",
          "(* not flagged successful.  Reference row: `benchmarks/inversion3d.py`, the full sphere box.)", "",
          "Targets:", ""]
    for r in runs:
        e3 = (r.get("3d") or {}).get("e")
        if e3 is not None:
            b = r.get("extent_mm") or [0, 0, 0, 0, 0, 0]
            scope = "" if b[1] - b[0] > 70 and b[3] - b[2] > 43 else " (stated for the whole imaged plane)"
            L.append(f"- {_extent(r)}: in-plane total strain error on the central plane, 3D {e3:.1f} % (2D "
                     f"{r['2d']['e']:.1f} %), target <= {TARGET_E:g} %{scope}: "
                     f"**{'met' if e3 <= TARGET_E else 'NOT met'}**")
        v = (r.get("inversion") or {}).get("3d_registered")
        if v is not None:
            ok = abs(v["contrast"] / 4.0 - 1.0) <= TARGET_CONTRAST
            L.append(f"- {_extent(r)}: 3D inversion of the registered 3D displacement, contrast {v['contrast']:.2f} "
                     f"(2D from the 2D registration {r['inversion']['2d_registered']['contrast']:.2f}), target "
                     f"3-5: **{'met' if ok else 'NOT met'}**")
    L += ["", "Reading the numbers:", ""]
    for r in runs:
        a, b = r["2d"], r.get("3d") or {}
        if not b:
            continue
        L.append(f"- {_extent(r)}: the 3D registration changes the in-plane total strain error by "
                 f"{b['e'] - a['e']:+.1f} points ({a['e']:.1f} -> {b['e']:.1f} %) and u_y by {b['uy'] - a['uy']:+.1f} "
                 f"points ({a['uy']:.1f} -> {b['uy']:.1f} %); the truth interpolated at the mesh nodes already errs by "
                 f"{a['floor_e']:.1f} % in 2D" + (f" and {b['floor_e']:.1f} % in 3D" if "floor_e" in b else "")
                 + " (the floor of elements of that size on this field)"
                 + (f", above the {TARGET_E:g} % target: at this element size no model reaches it."
                    if a["floor_e"] > TARGET_E else
                    f"; the 3D floor is above the {TARGET_E:g} % target: these hexahedra cannot reach it."
                    if b.get("floor_e", 0.0) > TARGET_E else "."))
        inv = r.get("inversion") or {}
        if "3d_exact" in inv and "3d_registered" in inv:
            L.append(f"- {_extent(r)}: the 3D inversion of the *exact* displacement over this region gives "
                     f"{inv['3d_exact']['contrast']:.2f} (the full sphere box: 4.14), of the registered one "
                     f"{inv['3d_registered']['contrast']:.2f}; the plane-stress 2D inversion "
                     f"{inv['2d_registered']['contrast']:.2f} (registered) and {inv['2d_exact']['contrast']:.2f} "
                     f"(exact).")
    L += [f"- {n}" for n in notes]
    L += ["", END]
    return L


def write_section(path: Path, runs: list, into: Path | None = None, notes=()) -> None:
    """Write the section to ``path``; with ``into``, also replace (or append) the marked block in that report."""
    lines = section(runs, notes)
    path.write_text("\n".join(lines) + "\n")
    if into is not None:
        text = into.read_text()
        block = "\n".join(lines)
        if BEGIN in text and END in text:
            a, b = text.index(BEGIN), text.index(END) + len(END)
            text = text[:a] + block + text[b:]
        else:
            text = text.rstrip("\n") + "\n\n" + block + "\n"
        into.write_text(text)


def _refine_value(v):
    try:
        return int(v) if v.isdigit() else float(v)
    except ValueError:
        return v            # a name ("axes=lateral")


def _refine_arg(text):
    """``--refine``: 'off' -> None, an integer -> that many passes, 'key=value,...' -> femreg's volume refinement
    (:data:`femreg.volume_refine.VOLUME_REFINEMENT`) with those options changed (numbers or names), 'plane' ->
    :data:`femreg.volume_refine.PLANE_REFINEMENT` ('plane,key=value,...': it with those changed), else the text
    ('auto')."""
    import dataclasses

    from femreg.volume_refine import PLANE_REFINEMENT, VOLUME_REFINEMENT

    if text == "off":
        return None
    base = VOLUME_REFINEMENT
    if text == "plane" or text.startswith("plane,"):
        base, text = PLANE_REFINEMENT, text[6:]
        if not text:
            return base
    if "=" in text:
        kw = dict(kv.split("=", 1) for kv in text.split(","))
        return dataclasses.replace(base, **{k: _refine_value(v) for k, v in kw.items()})
    return int(text) if text.isdigit() else text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inclusion", default="HI", choices=("HI", "mHI", "HOM", "SI"))
    ap.add_argument("--crop", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"))
    ap.add_argument("--quick", action="store_true", help="crop 20-42 x +-11 x +-5 mm around the inclusion")
    ap.add_argument("--regularizer", default="momentum-stress")
    ap.add_argument("--element-size", type=float, nargs="+", metavar="H",
                    help="element size mm of both registrations: one value, or axial lateral elevational (2D takes "
                    "the first two; default: femreg's, 2 mm)")
    ap.add_argument("--alpha-3d", type=float, help="alpha of the 3D registration (for 2 x 2 x 2 mm elements, "
                    "rescaled by femreg with the element volume; default: femreg's)")
    ap.add_argument("--refine", help="refine= of the 3D registration (femreg.volume_refine): 'auto', a number of "
                    "passes, or 'off' (default: femreg's)")
    ap.add_argument("--no-3d", action="store_true", help="the 2D registration only")
    ap.add_argument("--no-inversion", action="store_true", help="skip the 2D and 3D modulus inversions")
    ap.add_argument("--json", type=Path, help="write the numbers here")
    ap.add_argument("--section", type=Path, nargs="+", metavar=("OUT", "RUN_JSON"),
                    help="only write the report section OUT from the --json records RUN_JSON ... of earlier runs")
    ap.add_argument("--into", type=Path, help="with --section: also update the marked block of this report")
    ap.add_argument("--note", action="append", default=[], help="with --section: a line for its findings")
    ap.add_argument("--notes", type=Path, help="with --section: a file of findings lines, one per line")
    args = ap.parse_args(argv)
    if args.section:
        if len(args.section) < 2:
            raise InputError("--section needs OUT and at least one RUN_JSON")
        notes = list(args.note) + ([ln for ln in args.notes.read_text().splitlines() if ln.strip()]
                                   if args.notes else [])
        write_section(args.section[0], [json.loads(Path(j).read_text()) for j in args.section[1:]], args.into,
                      notes)
        print(f"wrote {args.section[0]}" + (f" and {args.into}" if args.into else ""))
        return 0
    box = args.crop or ((20.0, 42.0, -11.0, 11.0, -5.0, 5.0) if args.quick else None)

    t0 = time.perf_counter()
    seq = paper_volume_sequence(args.inclusion, frames=(0, 6), verbose=True)
    print(f"volumes {seq.frames.shape} (frames, axial, lateral, elevational), spacing {seq.spacing} mm, "
          f"{seq.params['n_scatterers']} scatterers, {time.perf_counter() - t0:.1f} s (cache: {seq.path})")
    sl, origin = crop(seq, box)
    ref, mov = (np.asarray(seq.frames[i][sl], np.float64) for i in (0, 1))
    field = seq.fields[1]
    k0 = int(np.argmin(np.abs(seq.grid.z[sl[2]])))
    z0 = float(seq.grid.z[sl[2]][k0])
    if abs(z0) > 1e-9:
        raise InputError(f"no elevational plane at z = 0 (nearest {z0:g} mm)")
    extent = [float(v) for a in range(3) for v in (seq.grid.axis(a)[sl[a]][[0, -1]])]
    out = {"inclusion": args.inclusion, "crop_mm": box, "extent_mm": extent, "shape": list(ref.shape),
           "spacing": list(seq.spacing),
           "regularizer": args.regularizer, "mean_axial_strain": seq.params["strain_schedule"][-1]}

    # 2D: the central plane, as the paper
    t0, c0 = time.perf_counter(), time.process_time()
    hs = args.element_size
    if hs is not None and len(hs) not in (1, 3):
        raise InputError(f"--element-size takes one or three values, got {len(hs)}")
    hs = None if hs is None else (hs * 3 if len(hs) == 1 else list(hs))
    out["element_size_mm"] = hs
    if args.alpha_3d is not None:
        out["alpha_3d"] = args.alpha_3d
    res2 = femreg.register(ref[:, :, k0], mov[:, :, k0], spacing=seq.spacing[:2], origin=origin[:2],
                           regularizer=args.regularizer, **({} if hs is None else {"element_size": tuple(hs[:2])}))
    t2 = time.perf_counter() - t0
    tu, te = plane_truth(field)
    e2 = {k: 100.0 * v for k, v in M.field_errors(res2, tu, te).items()}
    # the floor of the 2D mesh: the truth interpolated at its nodes, scored the same way (no images involved)
    u_t = M.interpolate_truth(res2.mesh, tu)
    floor = femreg.RegistrationResult(res2.mesh, u_t, shape=ref.shape[:2], spacing=seq.spacing[:2], origin=origin[:2])
    e2["floor_e"] = 100.0 * M.field_errors(floor, tu, te)["e"]
    out["2d"] = dict(e2, time_s=t2, cpu_s=time.process_time() - c0, peak_rss_mb=peak_rss_mb(),
                     success=bool(res2.success), message=res2.message)
    print(f"2D central plane ({args.regularizer}): {t2:.1f} s, success {res2.success}")
    # 3D, where femreg registers volumes
    res3 = None
    if not args.no_3d:
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            res3 = femreg.register(ref, mov, spacing=seq.spacing, origin=origin, regularizer=args.regularizer,
                                   **({} if hs is None else {"element_size": tuple(hs)}),
                                   **({} if args.alpha_3d is None else {"alpha": args.alpha_3d}),
                                   **({} if args.refine is None else {"refine": _refine_arg(args.refine)}))
            t3, c3 = time.perf_counter() - t0, time.process_time() - c0
            rss3 = peak_rss_mb()        # before the error evaluation (which runs in slabs)
        except InputError as exc:
            if "2D" not in str(exc):
                raise
            print(f"3D registration: not available in this femreg ({exc})")
            out["3d"] = None
        else:
            e3 = plane_errors_3d(res3, res2, field)
            e3.update(volume_errors_3d(res3, seq, 1, sl, origin))
            # the floor of the hexahedral mesh on the central plane: the truth at its nodes, scored the same way
            floor3 = femreg.VolumeResult(res3.mesh, field.displacement(res3.mesh.p.T).ravel(), shape=ref.shape,
                                         spacing=seq.spacing, origin=origin)
            e3["floor_e"] = plane_errors_3d(floor3, res2, field)["e"]
            out["3d"] = dict(e3, time_s=t3, cpu_s=c3, peak_rss_mb=rss3, peak_rss_errors_mb=peak_rss_mb(),
                             success=bool(res3.success), message=res3.message, nit=int(res3.nit),
                             elements=int(res3.mesh.t.shape[1]), timings=res3.timings)
            if args.refine is not None:
                out["refine"] = args.refine
            print(f"3D volumes ({args.regularizer}): {t3:.1f} s, success {res3.success}")

    if not args.no_inversion:
        region = inversion_region(seq, sl)
        out["inversion_region_mm"] = region
        out["inversion"] = inversions(res2, res3 if out.get("3d") else None, field, region)

    rows = [("u_x", "ux"), ("u_y", "uy"), ("u_z", "uz"), ("e_xx", "exx"), ("e_yy", "eyy"), ("e_xy", "exy"),
            ("in-plane total strain", "e"), ("six-component strain (volume)", "e6"),
            ("mesh floor, in-plane total", "floor_e")]
    print(f"\nerrors against the exact FE truth, frames 1 -> 7 ({100 * out['mean_axial_strain']:.2f} % mean axial "
          f"strain), %:")
    print(f"  {'':32s} {'2D':>8s} {'3D':>8s}")
    for label, key in rows:
        a = out["2d"].get(key)
        b = (out.get("3d") or {}).get(key)
        fmt = lambda v: f"{v:8.2f}" if v is not None else f"{'-':>8s}"  # noqa: E731
        print(f"  {label:32s} {fmt(a)} {fmt(b)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2, default=str))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
