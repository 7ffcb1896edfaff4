"""The femreg rows of benchmarks/inversion.py (the default path: cached registration -> ``femreg.invert`` defaults)
with module constants of :mod:`femreg.inversion` set, for studies of the debiasing options (TV_REWEIGHT_STEPS,
TV_BREGMAN, TV_BREGMAN_FRACTION, TV_BREGMAN_START; TV_REFIT and its TV_REFIT_* constants; docs/inversion.md,
"Contrast-preserving TV" and "Region debias refit"), and of the uncertainty's (SCATTER_FLOOR,
SCATTER_FLOOR_REFITTED; "Scatter floor on the uncertainty").

Same registrations (``$FEMREG_CACHE/bench_inversion/<key>``, which must hold every case: nothing is registered here),
the same contrast, ring, background CV and calibration as benchmarks/inversion.py, and per case the strain ratio read
as stiffness (``sr``: 1/SR, :func:`strain_ratio`, as benchmarks/inversion.py's 1/SR row), the modulus edge width
across the deep and the right edge (``edge_deep``, ``edge_right`` mm, :func:`edge_profile_width`; ``h``: the inversion
mesh's median element size), the modulus CNR (``cnr``) and the registered strain's (``cnr_strain``, |e_xx|, 1/SR's
source; :func:`sampled_cnr`); no NCC rows, the exact row (``exact``: edge widths and CNR only) with ``--exact``.

Usage: ``python benchmarks/inversion_debias_study.py OUT.json [CONST=VALUE ...] [--sets=main,held-out,...]
[--exact]``, then
``python benchmarks/inversion_debias_study.py --summary A.json B.json ...`` for the per-set counts (and the medians
and ranges of the edge widths and CNRs where recorded).  Rows of runs
from before ``sr`` was recorded: ``python benchmarks/inversion_debias_study.py --add-sr IN.json OUT.json`` adds it
from the cached registrations (no inversion).  ``--cv-detail IN.json [CASE ...]`` re-inverts the cases of IN.json
with a background CV above 15 % (or the cases named) and splits their ring (:func:`ring_parts`).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

SETS = ("main", "held-out", "fresh", "fresh2", "fresh3", "fresh4")


def strain_ratio(bench, reg, field):
    """1/SR: mean |e_xx| of the ring (1.6-2.5 R) over that of the disk (inside 0.7 R), the stiffness contrast users
    read off a strain image (benchmarks/inversion.py's 1/SR row)."""
    strain = lambda q: np.abs(reg.strain(q)[:, 0])  # noqa: E731
    return 1.0 / bench.sampled_contrast(strain, field.centre, field.radius_mm)[0]


def sampled_cnr(bench, fun, centre, R):
    """CNR = 2 (mean_in - mean_bg)^2 / (var_in + var_bg) of a callable points -> values, inside 0.7 R and in the
    ring 1.6-2.5 R (the regions and grid of the contrast, ``bench.sampled_regions``); NaN with fewer than 2
    samples in a region."""
    from femreg.metrics import cnr_e

    vin, vbg = bench.sampled_regions(fun, centre, R)      # finite samples only
    if len(vin) < 2 or len(vbg) < 2:
        return float("nan")
    return float(cnr_e(np.r_[vbg, vin], np.r_[np.zeros(len(vbg), bool), np.ones(len(vin), bool)]))


def edge_profile_width(fun, centre, R, direction, step=0.25, reach=2.0):
    """10-90 % width (mm) of the log of a positive callable points -> values (e.g. ``shear_modulus``) across a
    disk's edge: sampled every ``step`` mm from the ``centre`` (x, y mm) out to ``reach`` R along ``direction``
    ((1, 0): deeper, the deep edge; (0, 1): the right edge), cut at the first sample outside the mesh (non-finite),
    plateaus the medians of the profile's first and last fifth (:func:`femreg.metrics.edge_width`).  NaN when the
    profile stops before 1.6 R (no background plateau inside the mesh) or shows no step.  The estimate is constant
    per element: a step sharp to the element shows as a jump between two samples (0.2 mm), each element the edge
    crosses at an intermediate value adds about its size."""
    from femreg.metrics import edge_width

    s = np.arange(0.0, reach * R + 1e-9, step)
    d = np.asarray(direction, float) / np.hypot(*direction)
    v = np.asarray(fun(np.asarray(centre, float)[None, :] + s[:, None] * d[None, :]), float)
    bad = ~(np.isfinite(v) & (v > 0))
    n = int(np.argmax(bad)) if bad.any() else len(v)
    if n == 0 or s[n - 1] < 1.6 * R:
        return float("nan")
    x, y = s[:n], np.log(v[:n])
    n5 = max(1, n // 5)
    levels = (float(np.median(y[:n5])), float(np.median(y[-n5:])))
    if levels[0] == levels[1]:  # equal plateaus: no step to measure
        return float("nan")
    # the profile interpolated linearly on a grid 8 x finer: the same crossings, and a jump between two samples (an
    # element-constant modulus) read to 1/8 of a sample rather than to one sample
    fine = np.linspace(x[0], x[-1], 8 * (n - 1) + 1)
    return edge_width(fine, np.interp(fine, x, y), levels)


def median_element_size(mesh):
    """Median element extent (mm) along x (depth) and y (lateral) of a 2D mesh: (hx, hy)."""
    ext = mesh.p[:, mesh.t].max(axis=1) - mesh.p[:, mesh.t].min(axis=1)
    return tuple(float(e) for e in np.median(ext, axis=1))


def edge_cnr(bench, inv, field):
    """Edge widths (deep, right; mm, :func:`edge_profile_width`), modulus CNR and the inversion mesh's median
    element size (hx, hy mm) of one inversion result."""
    c, R = field.centre, field.radius_mm
    return dict(edge_deep=edge_profile_width(inv.shear_modulus, c, R, (1.0, 0.0)),
                edge_right=edge_profile_width(inv.shear_modulus, c, R, (0.0, 1.0)),
                cnr=sampled_cnr(bench, inv.shear_modulus, c, R), h=median_element_size(inv.mesh))


def _spec(bench, name, case):
    for spec in bench.SETS[name]:
        if bench.case_name(*spec) == case:
            return spec
    raise KeyError(f"{case} is not in the set {name}")


def add_sr(src, out):
    """Add ``sr`` (1/SR of the cached registration) to every row of ``src``; write ``out``."""
    import femreg
    import inversion as bench

    folder = bench.cache_folder()
    rows = json.loads(Path(src).read_text())
    for r in rows:
        m, c, pr, snr, rad, lev, seed = _spec(bench, r["set"], r["case"])
        reg = femreg.load_result(folder / f"{r['case']}.npz")
        r["sr"] = strain_ratio(bench, reg, bench.truth_field(m, c, lev, rad))
        print(f"{r['set']} {r['case']}: femreg ratio {r['ratio']:.3f}, 1/SR ratio {r['sr'] / c:.3f}", flush=True)
    Path(out).write_text(json.dumps(rows))


def ring_parts(fun, centre, R):
    """The ring (1.6-2.5 R) of a callable points -> values, split into the caps above and below the disk (the
    axial direction x, where a disk's strain lobes lie: |dx| > |dy|) and the sides: (CV of the whole ring, caps
    mean / sides mean, CV of the caps, CV of the sides).  Same 0.25 mm grid as ``sampled_contrast``."""
    g = np.arange(-2.5 * R, 2.5 * R + 1e-9, 0.25)
    X, Y = np.meshgrid(g, g, indexing="ij")
    X, Y = X.ravel(), Y.ravel()
    r = np.hypot(X, Y)
    v = fun(np.column_stack([X + centre[0], Y + centre[1]]))
    ring = (r > 1.6 * R) & (r < 2.5 * R) & np.isfinite(v)
    caps, sides = ring & (np.abs(X) > np.abs(Y)), ring & (np.abs(X) <= np.abs(Y))

    def cv(m):
        return float(np.std(v[m]) / np.mean(v[m]))
    return cv(ring), float(np.mean(v[caps]) / np.mean(v[sides])), cv(caps), cv(sides)


def cv_detail(src, limit=0.15, cases=()):
    """For every case of ``src`` with a background CV above ``limit`` (or named in ``cases``, e.g. cases below it
    for comparison): the registered and the exact displacement
    (the registration's mesh, its median element size, as benchmarks/inversion.py's exact row) inverted with the
    defaults, each ring split by :func:`ring_parts`; and the registered axial strain's error in the ring (RMS of
    e - e(truth) over the truth's mean |e|, axial e_xx and lateral e_yy)."""
    import femreg
    import inversion as bench

    folder = bench.cache_folder()
    for r in json.loads(Path(src).read_text()):
        if (r["case"] not in cases) if cases else r["cv"] <= limit:
            continue
        m, c, pr, snr, rad, lev, seed = _spec(bench, r["set"], r["case"])
        reg = femreg.load_result(folder / f"{r['case']}.npz")
        field = bench.truth_field(m, c, lev, rad)
        p = reg.mesh.p
        region = ((p[0].min(), p[0].max()), (p[1].min(), p[1].max()))
        ext = p[:, reg.mesh.t].max(axis=1) - p[:, reg.mesh.t].min(axis=1)
        h = tuple(np.median(ext, axis=1))
        out = []
        for name, inp, kw in (("femreg", reg, {}), ("exact", field.displacement, dict(region=region, element_size=h))):
            inv = femreg.invert(inp, **kw)
            est = bench.sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)[0] / c
            cvr, cs, cvc, cvs = ring_parts(inv.shear_modulus, field.centre, field.radius_mm)
            out.append(f"{name}: ratio {est:.2f}, ring CV {100 * cvr:.0f} % (caps {100 * cvc:.0f} %, sides "
                       f"{100 * cvs:.0f} %), caps / sides mean {cs:.2f}, beta {inv.beta:.3g}")
        R = field.radius_mm
        g = np.arange(-2.5 * R, 2.5 * R + 1e-9, 0.25)
        X, Y = np.meshgrid(g, g, indexing="ij")
        rr = np.hypot(X, Y).ravel()
        q = np.column_stack([X.ravel() + field.centre[0], Y.ravel() + field.centre[1]])[(rr > 1.6 * R) & (rr < 2.5 * R)]
        e_reg, e_true = reg.strain(q), field.strain(q)
        ok = np.isfinite(e_reg[:, 0])
        err = [float(np.sqrt(np.mean((e_reg[ok, k] - e_true[ok, k]) ** 2)) / np.mean(np.abs(e_true[ok, k])))
               for k in (0, 1)]
        print(f"{r['set']} {r['case']} (CV {100 * r['cv']:.1f} %, h {h[0]:.2f} x {h[1]:.2f} mm, R/h "
              f"{R / np.sqrt(h[0] * h[1]):.1f}): " + "; ".join(out)
              + f"; registered strain error in the ring (RMS / true mean |e|): e_xx {100 * err[0]:.0f} %, e_yy "
                f"{100 * err[1]:.0f} %", flush=True)


def run(out, settings, sets, exact=False):
    import femreg
    import femreg.inversion as inversion
    import inversion as bench

    for k, v in settings.items():
        setattr(inversion, k, v)
    rows = []
    for name, case, c, reg, field in bench.registered_cases(sets):
        t = time.perf_counter()
        inv = femreg.invert(reg)
        dt = time.perf_counter() - t
        est, cv = bench.sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)
        ring = bench.ring_coverage(inv.shear_modulus, field.centre, field.radius_mm)
        _, _, z = bench.calibration(inv, field, c)
        strain = lambda q: np.abs(reg.strain(q)[:, 0])  # noqa: E731
        row = dict(set=name, case=case, contrast=c, estimate=est, ratio=est / c, cv=cv, ring=ring,
                   success=bool(inv.success), beta=inv.beta, z=z, seconds=dt, misfit=inv.misfit,
                   rule=inv.beta_rule, uncertainty_calibrated=inv.uncertainty_calibrated,
                   uncertainty_scale=getattr(inv, "uncertainty_scale", None),
                   unsupported_area=inv.unsupported_area, flags=list(inv.flags), notes=list(inv.notes),
                   sr=strain_ratio(bench, reg, field), **edge_cnr(bench, inv, field),
                   cnr_strain=sampled_cnr(bench, strain, field.centre, field.radius_mm))
        if exact:
            # the forward model's displacement on the registration's mesh (benchmarks/inversion.py's exact row)
            p = reg.mesh.p
            region = ((p[0].min(), p[0].max()), (p[1].min(), p[1].max()))
            ex = femreg.invert(field.displacement, region=region, element_size=median_element_size(reg.mesh))
            row["exact"] = edge_cnr(bench, ex, field)
        rows.append(row)
        print(f"{name} {case}: ratio {est / c:.3f}, CV {100 * cv:.0f} %, beta {inv.beta:.3g}"
              f"{'' if inv.success else ', flagged'}, edge {row['edge_deep']:.2f} / {row['edge_right']:.2f} mm"
              f" (h {row['h'][0]:.2f} x {row['h'][1]:.2f}), CNR {row['cnr']:.1f} (strain "
              f"{row['cnr_strain']:.1f})" + (f", exact edge {row['exact']['edge_deep']:.2f} / "
                                            f"{row['exact']['edge_right']:.2f} mm" if exact else ""), flush=True)
        Path(out).write_text(json.dumps(rows))     # after every case: a cut-short run keeps what it measured


def summary(paths):
    """Per set: in the band (0.85-1.15, unflagged, measurable ring) / cases, CV <= 15 %, wrong side, calibration
    (over the elements of the cases with a measurable ring, as benchmarks/inversion.py's summary, and its range per
    case), results with ``uncertainty_calibrated`` False (all cases), the scatter floor's factor (median, range and
    the results it widened, where recorded: ``uncertainty_scale``); where rows hold ``sr``: stiff cases (contrast > 1,
    measurable ring) whose unflagged ratio is closer to 1 than 1/SR's, |log ratio| < |log (1/SR / contrast)|."""
    for p in paths:
        rows = json.loads(Path(p).read_text())
        print(f"**{p}**")
        tot = [0, 0, 0, 0, 0, 0]
        for name in dict.fromkeys(r["set"] for r in rows):
            rs = [r for r in rows if r["set"] == name and r["ring"] >= 0.5]
            band = sum(r["success"] and 0.85 <= r["ratio"] <= 1.15 for r in rs)
            cv = sum(r["cv"] <= 0.15 for r in rs)
            wrong = sum(r["success"] and (r["estimate"] - 1) * (r["contrast"] - 1) < 0
                        for r in rows if r["set"] == name)
            z = np.concatenate([np.asarray(r["z"], float) for r in rs] + [np.zeros(0)])
            uncal = sum(r.get("uncertainty_calibrated") is False for r in rows if r["set"] == name)
            stiff = [r for r in rs if r["contrast"] > 1 and "sr" in r]
            closer = sum(r["success"] and abs(np.log(r["ratio"])) < abs(np.log(r["sr"] / r["contrast"]))
                         for r in stiff)
            sr_txt = f", stiff closer than 1/SR {closer}/{len(stiff)}" if stiff else ""
            flagged = sum(not r["success"] for r in rows if r["set"] == name)
            un = [r.get("unsupported_area", np.nan) for r in rows if r["set"] == name]
            un_txt = (f", unsupported area largest {np.nanmax(un):.3f}" if np.isfinite(un).any() else "")
            per_case = [100 * np.mean(np.asarray(r["z"], float) <= 1) for r in rs if len(r["z"])]
            cal_txt = (f" (per case {min(per_case):.0f}-{max(per_case):.0f} %)" if per_case else "")
            scale = [r["uncertainty_scale"] for r in rows if r["set"] == name and r.get("uncertainty_scale")]
            scale_txt = (f", scatter floor factor {np.median(scale):.2f} ({min(scale):.2f}-{max(scale):.2f}), "
                         f"> 1 on {sum(x > 1 for x in scale)}/{len(scale)}" if scale else "")
            print(f"- {name}: {band}/{len(rs)} in the band, CV <= 15 % {cv}/{len(rs)}, wrong side {wrong}, "
                  f"within +-1 sigma {100 * np.mean(z <= 1):.1f} %{cal_txt}, uncertainty not calibrated {uncal}, "
                  f"flagged {flagged}{un_txt}{sr_txt}{scale_txt}")
            tot = [tot[0] + band, tot[1] + len(rs), tot[2] + cv, tot[3] + wrong, tot[4] + closer,
                   tot[5] + len(stiff)]
        edge_cnr_summary(rows)
        sr_txt = f", stiff closer than 1/SR {tot[4]}/{tot[5]}" if tot[5] else ""
        print(f"- total: {tot[0]}/{tot[1]} in the band, CV <= 15 % {tot[2]}/{tot[1]}, wrong side {tot[3]}{sr_txt}, "
              f"{sum(r['seconds'] for r in rows):.0f} s")


def _med_range(values):
    v = np.asarray([x for x in values if np.isfinite(x)], float)
    if not v.size:
        return "n/a"
    return f"{np.median(v):.2f} ({v.min():.2f}-{v.max():.2f})"


def edge_cnr_summary(rows):
    """Where rows hold the edge widths and CNR (runs from :func:`run` since they were added): per set and over all,
    median (range) of the deep and right edge widths (mm; in elements, over hx / hy), the modulus CNR and the
    strain's (|e_xx|, 1/SR's source) CNR, and the exact row's edge widths where recorded; cases whose ring is not
    measurable (< 50 % inside) are left out of the CNR."""
    if not rows or "edge_deep" not in rows[0]:
        return
    groups = [(name, [r for r in rows if r["set"] == name]) for name in dict.fromkeys(r["set"] for r in rows)]
    for name, rs in groups + [("all", rows)]:
        ms = [r for r in rs if r["ring"] >= 0.5]
        txt = (f"  - {name} edge width deep {_med_range(r['edge_deep'] for r in rs)} mm "
               f"[{_med_range(r['edge_deep'] / r['h'][0] for r in rs)} el], right "
               f"{_med_range(r['edge_right'] for r in rs)} mm [{_med_range(r['edge_right'] / r['h'][1] for r in rs)}"
               f" el]; CNR modulus {_med_range(r['cnr'] for r in ms)}, strain {_med_range(r['cnr_strain'] for r in ms)}"
               f", modulus > strain {sum(r['cnr'] > r['cnr_strain'] for r in ms)}/{len(ms)}")
        ex = [r["exact"] for r in rs if "exact" in r]
        if ex:
            txt += (f"; exact edge deep {_med_range(e['edge_deep'] for e in ex)}, right "
                    f"{_med_range(e['edge_right'] for e in ex)} mm, CNR {_med_range(e['cnr'] for e in ex)}")
        print(txt)


if __name__ == "__main__":
    args = sys.argv[1:]
    if args and args[0] == "--summary":
        summary(args[1:])
    elif args and args[0] == "--cv-detail":
        cv_detail(args[1], cases=tuple(args[2:]))
    elif args and args[0] == "--add-sr":
        add_sr(args[1], args[2])
    else:
        sets = SETS
        settings = {}
        exact = False
        for a in args[1:]:
            if a.startswith("--sets="):
                sets = tuple(a.split("=", 1)[1].split(","))
            elif a == "--exact":
                exact = True
            else:
                k, v = a.split("=", 1)
                settings[k] = json.loads(v)
        run(args[0], settings, sets, exact)
