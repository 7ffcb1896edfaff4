"""Modulus inversion from *registered* RF pairs: accuracy, honesty (flags), calibration of the uncertainty, beta.

Truths: a bonded disk at 20 mm depth in an 80 mm block (:data:`forward.fields.INCLUSION_MODEL`, radius from the
case), plane strain or plane stress; RF pairs of 30 x 30 mm from 5 mm depth (:func:`forward.pairs.make_pair`). Case
sets (:data:`SETS`, tuples (model, contrast, probe, SNR dB, radius mm, compression, seed)): ``main`` (radius 5 mm,
contrasts 0.25-4, 1 %, 20 dB, L7 and paper probes, seed 0: every constant of the rules was chosen on it; the element-size exponent of the beta target and the
calibration's 1/h on it and held-out),
``held-out`` (:data:`HELD_OUT`), ``fresh`` (:data:`FRESH`, drawn after the rule was fixed), ``fresh2``
(:data:`FRESH2`, drawn before the rule's second revision and not looked at until it was fixed), ``fresh3``
(:data:`FRESH3`, drawn before the soft-disk work, radii 4-8 mm, and not looked at until it was fixed), ``fresh4``
(:data:`FRESH4`, 14 cases drawn after fresh3's misses were diagnosed, first run with the code of that time), ``fresh5``
(:data:`FRESH5`, 20 cases drawn after the beta rule's step back, first run with the code of that time), ``curves``
(:data:`CURVES`, outside the targets' range), ``quick`` (4 L7 plane-strain main cases, for iteration). Each pair is
registered with femreg's defaults and inverted with ``femreg.invert`` defaults (``model="auto"``, beta by the
effective-parameter rule, uncertainty).

Rows per case:
- ``exact``: the forward model's own displacement on the same mesh;
- ``femreg``: the registered displacement (the default path);
- ``femreg base mesh``: the same registration inverted on the tensor mesh of the registration's unrefined element
  size (``refinement.base_size``) over its mesh's bounding box (``region`` given, no ``element_size``);
- ``femreg growth``: the same with the former beta rule (``beta_method="growth"``);
- ``femreg one-step``: the default path followed by the one-step inversion from the images (same beta);
- ``NCC``: NCC block matching's displacement (:data:`NCC_WINDOW`, 75 % overlap) on the same element size;
- ``1/SR``: the strain ratio users read as stiffness, mean |e_xx| of the ring over that of the disk.

Metrics: mean modulus sampled inside 0.7 R of the centre over the mean in the ring 1.6-2.5 R (points every
0.25 mm); its ratio to the truth; background CV (std / mean of the ring samples); the ring's fraction inside the
mesh (``ring``: below :data:`RING_MEASURABLE` the case is reported as "ring not measurable" and left out of the
band count); flags (``success``);
calibration: fraction of constrained elements whose true relative log mu (disk contrast or 1 at the element
centre) lies within +-1 sigma, with |z| per element kept in the JSON rows; beta: the contrast ratio of the rule's
beta against that of the truth-best beta of the grid (fixed-beta inversions), "within 15 %" meaning
|ratio_rule / ratio_best - 1| <= 0.15.  Speed: one paper-probe pair of 70 x 42 mm, registered, inverted with the
rule and the uncertainty.

Usage: ``python benchmarks/inversion.py [--quick] [--set main --set curves ...] [--rows exact,femreg]
[--json rows.json] [--from-json rows.json] [--figure curves.png] [--out table.md]``.  Registrations are cached
under ``$FEMREG_CACHE/bench_inversion/defaults-KEY`` (:func:`cache_folder`: by case name, within a folder keyed
by register's defaults and its default refinement; after other changes of the registration code, empty it).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import femreg  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.elasticity import cache_dir, cached_solve  # noqa: E402
from forward.pairs import make_pair  # noqa: E402

BACKGROUND_E = 10.0
CONTRASTS = (0.25, 0.5, 2.0, 4.0)
#: (probe, SNR dB); every probe / SNR runs every contrast and model
SETTINGS = (("L7", 20.0), ("paper", 20.0))
QUICK_SETTINGS = (("L7", 20.0),)
MODELS = ("plane-strain", "plane-stress")
#: Held out: cases no rule or constant was chosen on (other probes, seeds, radii, compressions and SNRs), inside the
#: targets' range (2D truths, radius >= 4 mm, SNR >= 15 dB, contrast 0.25-4): (model, contrast, probe, snr, radius
#: mm, compression, seed).
HELD_OUT = tuple((m, c, pr, snr, r, lev, seed)
                 for m in MODELS
                 for c, pr, snr, r, lev, seed in ((0.25, "L3", 20.0, 5.0, 0.01, 1), (4.0, "L3", 20.0, 5.0, 0.01, 1),
                                                  (0.5, "L12", 15.0, 4.0, 0.01, 2), (2.0, "L12", 15.0, 4.0, 0.01, 2),
                                                  (0.25, "L7", 30.0, 6.0, 0.02, 3), (4.0, "L7", 30.0, 6.0, 0.02, 3),
                                                  (0.5, "L15", 25.0, 5.0, 0.04, 4), (4.0, "paper", 15.0, 4.0, 0.02, 5)))
#: Fresh: drawn after the beta rule's form and constant were fixed (on the main set, its form checked on HELD_OUT),
#: new seeds and combinations, inside the targets' range.
FRESH = tuple((m, c, pr, snr, r, lev, seed)
              for m in MODELS
              for c, pr, snr, r, lev, seed in ((0.5, "L3", 25.0, 6.0, 0.01, 11), (2.0, "L3", 15.0, 4.0, 0.02, 12),
                                               (0.25, "L12", 20.0, 5.0, 0.01, 13), (4.0, "L12", 30.0, 6.0, 0.03, 14),
                                               (2.0, "L7", 20.0, 4.0, 0.01, 15), (0.25, "paper", 25.0, 6.0, 0.01, 16),
                                               (0.5, "L7", 15.0, 4.0, 0.04, 17), (2.0, "paper", 30.0, 5.0, 0.02, 18)))
#: Fresh2: drawn before the beta rule's second revision (the target between per-area and per-element) and not looked
#: at until that rule was fixed; new seeds 21-28, contrasts off the main set's grid (0.35, 3) among them, every probe.
FRESH2 = tuple((m, c, pr, snr, r, lev, seed)
               for m in MODELS
               for c, pr, snr, r, lev, seed in ((0.25, "L15", 20.0, 5.0, 0.02, 21), (3.0, "L12", 25.0, 4.0, 0.01, 22),
                                                (0.5, "L3", 30.0, 5.0, 0.03, 23), (4.0, "L15", 15.0, 6.0, 0.01, 24),
                                                (0.35, "paper", 20.0, 4.0, 0.04, 25), (4.0, "L7", 25.0, 5.0, 0.03, 26),
                                                (2.0, "L12", 30.0, 6.0, 0.02, 27), (0.25, "L7", 15.0, 4.0, 0.02, 28)))
#: Fresh3: drawn before the soft-disk work (the inversion's forward model and mesh) and not looked at until it was
#: fixed; new seeds 41-48, every probe, radii 4-8 mm, contrasts 0.25-4 off the former grids (0.3, 0.4, 2.5), five
#: of eight soft.
FRESH3 = tuple((m, c, pr, snr, r, lev, seed)
               for m in MODELS
               for c, pr, snr, r, lev, seed in ((0.25, "L3", 25.0, 6.0, 0.02, 41), (0.3, "paper", 20.0, 7.0, 0.01, 42),
                                                (0.5, "L7", 20.0, 8.0, 0.02, 43), (0.4, "L12", 15.0, 5.0, 0.03, 44),
                                                (0.25, "L15", 30.0, 4.0, 0.01, 45), (3.0, "L3", 20.0, 4.0, 0.03, 46),
                                                (2.5, "paper", 30.0, 6.0, 0.02, 47), (4.0, "L12", 25.0, 7.0, 0.01, 48)))
#: Fresh4: drawn before the work after fresh3 and run once with the code of that time before any change; new seeds
#: 51-57, every probe, radii 4-7 mm off the former grids (4.5, 5.5, 6.5), contrasts 0.25-4 (0.35, 0.6, 1.5, 3.5 new),
#: 1-4 %, 15-30 dB, both models: 14 cases.
FRESH4 = tuple((m, c, pr, snr, r, lev, seed)
               for m in MODELS
               for c, pr, snr, r, lev, seed in ((0.35, "L3", 20.0, 5.0, 0.02, 51), (2.0, "L15", 25.0, 4.5, 0.02, 52),
                                                (0.6, "paper", 25.0, 5.5, 0.03, 53), (3.5, "L7", 15.0, 6.0, 0.01, 54),
                                                (0.25, "L12", 30.0, 4.0, 0.04, 55), (1.5, "L3", 30.0, 6.5, 0.01, 56),
                                                (4.0, "paper", 20.0, 7.0, 0.02, 57)))
#: Drawn after the beta rule's step back (seeded draws, numpy default_rng 20261207: contrast log-uniform 0.25-4, any
#: probe, SNR 15-30 dB, radius 4-8 mm, 1-4 %; then rng 202612071: three soft disks 0.25-0.6 under L3, where the
#: misses of the sets before sat), first run with the code of that time.
FRESH5 = tuple((m, c, pr, snr, r, lev, seed)
               for m in MODELS
               for c, pr, snr, r, lev, seed in ((2.83, "L7", 25.0, 5.5, 0.03, 61), (0.9, "L7", 30.0, 5.5, 0.02, 62),
                                                (1.03, "paper", 30.0, 4.5, 0.01, 63), (0.6, "L15", 25.0, 6.5, 0.03, 64),
                                                (2.52, "L12", 25.0, 8.0, 0.01, 65), (0.25, "L7", 15.0, 4.5, 0.01, 66),
                                                (1.17, "L7", 15.0, 5.0, 0.01, 67), (0.49, "L3", 30.0, 7.0, 0.03, 68),
                                                (0.46, "L3", 15.0, 6.5, 0.03, 69), (0.51, "L3", 30.0, 7.0, 0.04, 70)))
#: Outside the targets' range, for the contrast-recovery curves (plane strain, L7, 1 %, seed 6, one parameter
#: varied from the 5 mm / 20 dB / contrast 4 or 0.25 case): radius, contrast, SNR.
CURVES = (tuple(("plane-strain", c, "L7", 20.0, r, 0.01, 6) for c in (0.25, 4.0) for r in (1.5, 2.5, 3.5, 8.0))
          + tuple(("plane-strain", c, "L7", 20.0, 5.0, 0.01, 6) for c in (0.125, 8.0))
          + tuple(("plane-strain", c, "L7", snr, 5.0, 0.01, 6) for c in (0.25, 4.0) for snr in (10.0, 30.0)))
SIZE, TOP = (30.0, 30.0), 5.0
#: NCC block matching window (axial, lateral) mm
NCC_WINDOW = (2.0, 3.0)


def truth_field(model, contrast, level=0.01, radius=5.0):
    params = dict(F.INCLUSION_MODEL, inclusion_modulus=BACKGROUND_E * contrast, compression_mm=1.0)
    if radius != 5.0:   # as forward.fields.Inclusion refines the FE mesh for its radius
        params.update(inclusion_diameter_mm=2.0 * radius, mesh_size_mm=min(params["mesh_size_mm"], 0.25 * radius))
    sol = cached_solve(model, **params)
    return F.Inclusion("stiff", model, level, radius_mm=None if radius == 5.0 else radius, _solution=sol)


def case_name(model, contrast, probe, snr, radius=5.0, level=0.01, seed=0):
    """Cache key and label: the original 16 cases keep their short names."""
    name = f"{model}-{contrast:g}_{probe}_{snr:g}"
    if radius != 5.0:
        name += f"_r{radius:g}"
    if level != 0.01:
        name += f"_c{100 * level:g}"
    if seed:
        name += f"_s{seed}"
    return name


def sampled_regions(fun, centre, R):
    """Values of a callable points -> values inside 0.7 R and in the ring 1.6-2.5 R of a disk of radius ``R`` mm
    at ``centre`` (x, y mm), on a 0.25 mm grid, non-finite samples (outside the mesh) dropped: (inner, ring)."""
    g = np.arange(-2.5 * R, 2.5 * R + 1e-9, 0.25)
    X, Y = np.meshgrid(g, g, indexing="ij")
    r = np.hypot(X, Y).ravel()
    pts = np.column_stack([X.ravel() + centre[0], Y.ravel() + centre[1]])
    v = fun(pts)
    inner, ring = (r < 0.7 * R) & np.isfinite(v), (r > 1.6 * R) & (r < 2.5 * R) & np.isfinite(v)
    return v[inner], v[ring]


def sampled_contrast(fun, centre, R):
    """(contrast, background CV) of a callable points -> values: mean inside 0.7 R over mean in 1.6-2.5 R."""
    vin, vring = sampled_regions(fun, centre, R)
    return float(np.mean(vin) / np.mean(vring)), float(np.std(vring) / np.mean(vring))


#: The ring (1.6-2.5 R) is measurable when at least this fraction of its sample points lies inside the inversion
#: mesh: with less, its mean is that of the caps above and below the disk (where a disk's strain lobes lie), not a
#: ring's, and the contrast as the targets define it cannot be evaluated (reported, not counted in the band).
RING_MEASURABLE = 0.5


def ring_coverage(fun, centre, R):
    """Fraction of the ring's sample points (1.6-2.5 R, the grid of :func:`sampled_contrast`) where ``fun`` is
    finite, i.e. inside the mesh."""
    g = np.arange(-2.5 * R, 2.5 * R + 1e-9, 0.25)
    X, Y = np.meshgrid(g, g, indexing="ij")
    r = np.hypot(X, Y).ravel()
    ring = (r > 1.6 * R) & (r < 2.5 * R)
    pts = np.column_stack([X.ravel() + centre[0], Y.ravel() + centre[1]])[ring]
    return float(np.mean(np.isfinite(fun(pts))))


def registered_cases(sets, skip=()):
    """``(set, case name, contrast, registration result, truth field)`` of every case of the named ``sets`` from
    the cache (:func:`cache_folder`), leaving out the ``(set, case name)`` pairs in ``skip``; SystemExit naming the
    first case not registered yet."""
    folder = cache_folder()
    for name in sets:
        for (m, c, pr, snr, r, lev, seed) in SETS[name]:
            case = case_name(m, c, pr, snr, r, lev, seed)
            if (name, case) in skip:
                continue
            path = folder / f"{case}.npz"
            if not path.exists():
                raise SystemExit(f"{path}: not registered (run benchmarks/inversion.py --set {name} first)")
            yield name, case, c, femreg.load_result(path), truth_field(m, c, lev, r)


def cache_folder():
    """The registrations' cache: ``$FEMREG_CACHE/bench_inversion/<key>``, the key a hash of ``femreg.register``'s
    signature (its defaults), the default refinement's name and the rules it stands for
    (:data:`femreg.refine.DEEP_REFINEMENT`) and R_P_sigma's options under strategy="auto" with the rule its
    lambda_bar follows (:mod:`femreg.strategy`), so a change of the registration defaults or of the refinement
    rules registers again instead of reusing results of the former defaults."""
    import hashlib
    import inspect

    from femreg import strategy as S
    from femreg.refine import DEEP_REFINEMENT
    from femreg.refine import DEFAULT as default_refine

    # the default is a name ("default"): the rules it stands for key the cache too
    rules = (S.DEFAULT_MOMENTUM_STRESS_OPTIONS, S.LAMBDA_BAR_MODELS, S.PLANE_STRAIN_RATIO, S.AXIAL_SHARE, S.RATIO_MAX,
             inspect.getsource(S.data_lambda_bar))
    key = hashlib.sha1((str(inspect.signature(femreg.register)) + repr(default_refine)
                        + repr(DEEP_REFINEMENT) + repr(rules)).encode()).hexdigest()[:10]
    folder = cache_dir() / "bench_inversion" / f"defaults-{key}"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def register(case, field, probe, snr, seed=0):
    folder = cache_folder()
    path = folder / f"{case}.npz"
    if path.exists():
        return femreg.load_result(path), float("nan")
    pair = make_pair(field, probe, SIZE, snr, seed, top_mm=TOP, name=case)
    t = time.perf_counter()
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
    dt = time.perf_counter() - t
    res.save(path)
    return res, dt


def calibration(inv, field, contrast, uncut=False):
    """(fraction within +-1 sigma, elements, |z| per element); ``uncut``: only elements not cut by the disk's edge
    (whose true value, a mix of two moduli, is not defined by the centre)."""
    if inv.uncertainty is None:
        return np.nan, 0, []
    c = inv.centroids
    true = np.where(field.inside(c), np.log(contrast), 0.0)
    ok = inv.constrained & np.isfinite(inv.uncertainty)
    if uncut:
        node_in = field.inside(inv.mesh.p.T)[inv.mesh.t]
        ok &= node_in.all(axis=0) | (~node_in).all(axis=0)
    z = np.abs(np.log(inv.mu[ok]) - true[ok]) / inv.uncertainty[ok]
    return float(np.mean(z <= 1.0)), int(ok.sum()), z.tolist()


def _block_matching(pair, reg):
    """NCC block matching's displacement (2 x 3 mm windows, 75 % overlap: a vector every 0.5 x 0.75 mm, finer than
    femreg.blockmatch's default 5 x 9 mm windows, whose 7 x 4 vectors over these images cannot show a 5 mm disk) and
    the region it covers inside the mesh."""
    from femreg.blockmatch import block_match

    bm = block_match(pair.ref, pair.mov, pair.spacing, pair.origin, window=NCC_WINDOW, overlap=(0.75, 0.75))
    p = reg.mesh.p
    region = ((max(p[0].min(), bm.x.min()), min(p[0].max(), bm.x.max())),
              (max(p[1].min(), bm.y.min()), min(p[1].max(), bm.y.max())))
    return bm, region


def run_case(model, contrast, probe, snr, radius=5.0, level=0.01, seed=0, beta_study=True, rows_wanted=None):
    case = case_name(model, contrast, probe, snr, radius, level, seed)
    field = truth_field(model, contrast, level, radius)
    reg, t_reg = register(case, field, probe, snr, seed)
    centre, R = field.centre, field.radius_mm
    rows = []
    p = reg.mesh.p
    region = ((p[0].min(), p[0].max()), (p[1].min(), p[1].max()))
    ext = p[:, reg.mesh.t].max(axis=1) - p[:, reg.mesh.t].min(axis=1)
    h = tuple(np.median(ext, axis=1))
    pair = make_pair(field, probe, SIZE, snr, seed, top_mm=TOP, name=case)
    todo = [("exact", lambda: field.displacement, lambda: dict(region=region, element_size=h)),
            ("femreg", lambda: reg, dict),
            ("femreg base mesh", lambda: reg, lambda: dict(region=region)),
            ("femreg growth", lambda: reg, lambda: dict(beta_method="growth")),
            ("femreg one-step", lambda: reg, lambda: dict(reference_image=pair.ref, moving_image=pair.mov))]
    bm = []
    todo.append(("NCC", lambda: bm[0][0], lambda: dict(region=bm[0][1], element_size=h)))
    for name, inp_f, kw_f in todo:
        if rows_wanted is not None and name not in rows_wanted:
            continue
        if name == "NCC":
            bm.append(_block_matching(pair, reg))
        inp, kw = inp_f(), kw_f()
        t = time.perf_counter()
        inv = femreg.invert(inp, **kw)
        dt = time.perf_counter() - t
        cest, cv = sampled_contrast(inv.shear_modulus, centre, R)
        ring = ring_coverage(inv.shear_modulus, centre, R)
        cal, ncal, z = calibration(inv, field, contrast)
        calu, ncalu, _ = calibration(inv, field, contrast, uncut=True)
        row = dict(case=case, model=model, contrast=contrast, probe=probe, snr=snr, radius=radius, level=level,
                   seed=seed, row=name, estimate=cest, ratio=cest / contrast, cv=cv, ring=ring, success=inv.success,
                   flags="; ".join(inv.flags), chosen_model=inv.model, beta=inv.beta, cal=cal, ncal=ncal,
                   calu=calu, ncalu=ncalu, z=z if name in ("femreg", "femreg base mesh") else [], seconds=dt,
                   misfit=inv.misfit, n_el=int(inv.mesh.t.shape[1]), element_mm=float(np.sqrt(h[0] * h[1])),
                   unsupported_area=inv.unsupported_area, notes="; ".join(inv.notes))
        if beta_study and name == "femreg":
            best = None
            up = femreg.inversion.BETA_GRID[0] * 10.0 ** (0.5 * np.arange(femreg.inversion.DOF_UP_STEPS, 0, -1))
            for b in tuple(up) + femreg.inversion.BETA_GRID:
                fi = femreg.invert(inp, beta=b, uncertainty=False, **kw)
                rb = sampled_contrast(fi.shear_modulus, centre, R)[0] / contrast
                if best is None or abs(np.log(rb)) < abs(np.log(best[1])):
                    best = (b, rb)
            row.update(best_beta=best[0], best_ratio=best[1])
        rows.append(row)
    strain = lambda q: np.abs(reg.strain(q)[:, 0])  # noqa: E731
    s_in_over_ring = sampled_contrast(strain, centre, R)[0]
    sr = 1.0 / s_in_over_ring
    rows.append(dict(case=case, model=model, contrast=contrast, probe=probe, snr=snr, radius=radius, level=level,
                     seed=seed, row="1/SR", estimate=sr, ratio=sr / contrast, cv=np.nan, success=True, flags="",
                     chosen_model="", beta=np.nan, cal=np.nan, ncal=0, calu=np.nan, ncalu=0, z=[], seconds=np.nan,
                     misfit=np.nan, n_el=0, element_mm=np.nan))
    return rows


def regularizer_cases():
    """The stiff plane-strain disk (x4, 1 %, L7, 30 dB) registered with R_P_sigma, R_P_eps and R_eps, inverted
    with each model: (regulariser, model asked, model used, contrast, success, flags) rows."""
    field = truth_field("plane-strain", 4.0)
    folder = cache_folder()
    out = []
    pair = None
    for regname in ("momentum-stress", "momentum-strain", "strain"):
        path = folder / f"regularizer_{regname}.npz"
        if path.exists():
            reg = femreg.load_result(path)
        else:
            if pair is None:
                pair = make_pair(field, "L7", SIZE, 30.0, 0, top_mm=TOP)
            reg = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, regularizer=regname)
            reg.save(path)
        for model in ("auto", "plane-stress", "plane-strain"):
            inv = femreg.invert(reg, model=model)
            c = sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)[0]
            out.append((regname, model, inv.model, c, inv.success, "; ".join(inv.flags)[:100]))
    return out


def speed(one_step=False):
    """Seconds of ``femreg.invert`` (beta rule, uncertainty) on the paper-probe 70 x 42 mm registered pair, the
    inversion mesh's element count and the result; ``one_step``: also the CPU seconds (``time.process_time``) of
    the two-step and of the one-step inversion from the images (same beta rule, no uncertainty) and their results."""
    field = truth_field("plane-strain", 4.0)
    folder = cache_folder()
    path = folder / "speed_paper_70x42.npz"
    pair = make_pair(field, "paper", (70.0, 42.0), 20.0, 0, top_mm=2.0)
    if path.exists():
        reg = femreg.load_result(path)
    else:
        reg = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
        reg.save(path)
    t = time.perf_counter()
    inv = femreg.invert(reg)
    out = (time.perf_counter() - t, inv.mesh.t.shape[1], inv)      # the inversion mesh's elements
    if not one_step:
        return out
    rows = []
    for kw in ({}, dict(reference_image=pair.ref, moving_image=pair.mov)):
        c0 = time.process_time()
        r = femreg.invert(reg, uncertainty=False, **kw)
        rows.append((time.process_time() - c0, r, sampled_contrast(r.shear_modulus, field.centre, field.radius_mm)))
    return out + (rows,)


def _pct(v):
    return "" if not np.isfinite(v) else f"{100 * v:.0f} %"


def _g(v):
    return "" if not np.isfinite(v) else f"{v:.3g}"


def table(rows):
    out = ["| case | row | model chosen | contrast | ratio to truth | background CV | success | beta | "
           "truth-best beta (ratio) | within +-1 sigma | flags |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        bb = f"{r['best_beta']:.3g} ({r['best_ratio']:.2f})" if "best_beta" in r else ""
        out.append(f"| {r['case']} | {r['row']} | {r['chosen_model']} | {r['estimate']:.2f} | {r['ratio']:.2f}"
                   f"{'' if measurable(r) else ' (ring not measurable)'} | "
                   f"{_pct(r['cv'])} | {r['success']} | {_g(r['beta'])} | {bb} | {_pct(r['cal'])} | "
                   f"{r['flags'][:90]} |")
    return "\n".join(out)


def in_targets(r):
    """The targets' range: 2D truth, radius >= 4 mm, SNR >= 15 dB, contrast 0.25-4."""
    return r["radius"] >= 4.0 and r["snr"] >= 15.0 and 0.25 <= r["contrast"] <= 4.0


def _band(r):
    return bool(r["success"]) and 0.85 <= r["ratio"] <= 1.15


def measurable(r):
    """The ring lies inside the image enough to define the contrast (:data:`RING_MEASURABLE`); rows of runs
    before the coverage was recorded count as measurable."""
    return r.get("ring", 1.0) >= RING_MEASURABLE


def summary(rows, label="", row="femreg"):
    """The metrics of ``row`` (the default path, or another row of the same pairs such as ``femreg base mesh``)."""
    fem = [r for r in rows if r["row"] == row]
    if not fem:
        return ""
    sr = {r["case"]: r for r in rows if r["row"] == "1/SR"}
    by = {(r["case"], r["row"]): r for r in rows}
    unmeasurable = [r for r in fem if not measurable(r)]
    fem_all, fem = fem, [r for r in fem if measurable(r)]
    acc = [r for r in fem if _band(r)]
    wrong = [r for r in rows if r["row"] != "1/SR"
             if r["success"] and (r["estimate"] - 1) * (r["contrast"] - 1) < 0]
    stiff = [r for r in fem if r["contrast"] > 1]
    closer = [r for r in stiff if r["success"] and abs(np.log(r["ratio"])) < abs(np.log(sr[r["case"]]["ratio"]))]
    lines = [f"**{label}** ({len(fem)} cases)", "",
             f"- {row} rows: {len(acc)}/{len(fem)} unflagged with ratio 0.85-1.15 (flagged count as misses); "
             f"{sum(not r['success'] for r in fem)} flagged"]
    if unmeasurable:
        lines[0] = f"**{label}** ({len(fem_all)} cases, {len(fem)} with a measurable ring)"
        lines.append(f"- ring not measurable (less than {100 * RING_MEASURABLE:.0f} % of the 1.6-2.5 R ring inside "
                     "the image), reported and not counted: " + ", ".join(
                         f"{r['case']} (ring {100 * r['ring']:.0f} % inside, ratio {r['ratio']:.2f}"
                         f"{'' if r['success'] else ', flagged'})" for r in unmeasurable))
        lines.append(f"- {row} rows counting every case: {sum(_band(r) for r in fem_all)}/{len(fem_all)}")
    for other in ("femreg", "femreg base mesh", "femreg growth", "femreg one-step", "NCC", "exact"):
        if other == row:
            continue
        o = [by[(r["case"], other)] for r in fem if (r["case"], other) in by]
        if o:
            lines.append(f"- {other}: {sum(_band(x) for x in o)}/{len(o)} in the band "
                         f"({sum(not x['success'] for x in o)} flagged)")
    os_ = [(by[(r["case"], "femreg one-step")], r) for r in fem if (r["case"], "femreg one-step") in by]
    if os_:
        lines.append(f"- one-step closer to the truth than two-step on "
                     f"{sum(abs(np.log(o['ratio'])) < abs(np.log(f['ratio'])) for o, f in os_)}/{len(os_)}; slowest "
                     f"{max(o['seconds'] for o, _ in os_):.1f} s (two-step included)")
    beta = [r for r in fem if "best_ratio" in r]
    beta_ok = [r for r in beta if abs(r["ratio"] / r["best_ratio"] - 1) <= 0.15]
    cv_ok = [r for r in fem if r["cv"] <= 0.15]
    z = np.concatenate([np.asarray(r["z"], float) for r in fem] + [np.zeros(0)])
    cal_ex = [r for r in rows if r["row"] == "exact" and r["ncal"]]
    cal_ex_v = sum(r["cal"] * r["ncal"] for r in cal_ex) / max(sum(r["ncal"] for r in cal_ex), 1)
    calu_n = sum(r["ncalu"] for r in fem)
    calu = sum(r["calu"] * r["ncalu"] for r in fem if r["ncalu"]) / max(calu_n, 1)
    lines += [f"- wrong side of 1 with success=True (all inversion rows): {len(wrong)}",
              f"- stiff cases closer than 1/SR (unflagged): {len(closer)}/{len(stiff)}",
              f"- background CV <= 15 %: {len(cv_ok)}/{len(fem)}",
              f"- beta rule within 15 % of the truth-best beta's contrast ratio: {len(beta_ok)}/{len(beta)}",
              f"- calibration (true log mu within +-1 sigma): femreg {100 * np.mean(z <= 1):.0f} % of {z.size} "
              f"elements (68 % of them within +-{np.quantile(z, 0.68):.2f} sigma); exact "
              f"{100 * cal_ex_v:.0f} %; femreg without the elements cut by the disk's edge {100 * calu:.0f} %",
              f"- misfit at the chosen beta (units of (strain h)^2): {min(r['misfit'] for r in fem):.2g}-"
              f"{max(r['misfit'] for r in fem):.2g}; slowest femreg inversion {max(r['seconds'] for r in fem):.1f} s "
              f"({max(r['n_el'] for r in fem)} elements at most)", ""]
    return "\n".join(lines)


def curves_figure(rows, path):
    """Contrast ratio (estimate / truth) of the default path against radius, contrast and SNR (CURVES cases and
    the main L7 plane-strain cases at their default parameters)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401

    fem = [r for r in rows if r["row"] in ("femreg", "1/SR") and r["model"] == "plane-strain" and r["probe"] == "L7"
           and r["level"] == 0.01]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), constrained_layout=True)
    specs = (("radius", "inclusion radius (mm)", lambda r: r["snr"] == 20.0),
             ("contrast", "true contrast", lambda r: r["snr"] == 20.0 and r["radius"] == 5.0),
             ("snr", "SNR (dB)", lambda r: r["radius"] == 5.0))
    for ax, (key, xlabel, keep) in zip(axes, specs):
        for which, style in (("femreg", "o-"), ("1/SR", "s:")):
            for c_sel, colour in ((lambda c: c < 1, "tab:blue"), (lambda c: c > 1, "tab:red")):
                if key != "contrast":
                    sel = sorted((r for r in fem if r["row"] == which and keep(r) and c_sel(r["contrast"])
                                  and r["contrast"] in (0.25, 4.0)), key=lambda r: r[key])
                else:
                    sel = sorted((r for r in fem if r["row"] == which and keep(r) and c_sel(r["contrast"])),
                                 key=lambda r: r[key])
                if not sel:
                    continue
                x = [r[key] for r in sel]
                y = [r["ratio"] for r in sel]
                ax.plot(x, y, style, color=colour, mfc="none" if which == "1/SR" else colour,
                        label=f"{which} {'soft' if c_sel(0.5) and colour == 'tab:blue' else 'stiff'}")
                if which == "femreg":
                    for xi, yi, r in zip(x, y, sel):
                        if not r["success"]:
                            ax.plot(xi, yi, "x", color="k", ms=9)
        ax.axhspan(0.85, 1.15, color="0.9", zorder=0)
        ax.axhline(1.0, color="0.5", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_yscale("log")
        ticks = [0.4, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0]
        ax.yaxis.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
        ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.yaxis.set_major_formatter(matplotlib.ticker.FixedFormatter([f"{t:g}" for t in ticks]))
        if key == "contrast":
            ax.set_xscale("log")
            xt = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0]
            ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(xt))
            ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
            ax.xaxis.set_major_formatter(matplotlib.ticker.FixedFormatter([f"{t:g}" for t in xt]))
    axes[0].set_ylabel("estimate / truth (x: flagged)")
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle("Contrast recovery of femreg.invert's default path (plane strain, L7, 1 %); "
                 "grey band 0.85-1.15")
    fig.savefig(path, dpi=90)
    plt.close(fig)


SETS = {"main": tuple((m, c, pr, snr, 5.0, 0.01, 0) for pr, snr in SETTINGS for m in MODELS for c in CONTRASTS),
        "held-out": HELD_OUT, "fresh": FRESH, "fresh2": FRESH2, "fresh3": FRESH3, "fresh4": FRESH4, "fresh5": FRESH5, "curves": CURVES,
        "quick": tuple(("plane-strain", c, "L7", 20.0, 5.0, 0.01, 0) for c in CONTRASTS)}


def main(argv=None):
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", choices=tuple(SETS), help="case set(s) (default: main)")
    ap.add_argument("--quick", action="store_true", help="the quick set (4 L7 plane-strain cases), no extras")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--speed-only", action="store_true", help="only the speed rows (two-step and one-step)")
    ap.add_argument("--no-beta-study", action="store_true", help="skip the fixed-beta sweeps")
    ap.add_argument("--no-regularizers", action="store_true", help="skip the regulariser table of the main set")
    ap.add_argument("--json", help="write the rows (all metrics) to this JSON file")
    ap.add_argument("--rows", help="comma-separated inversion rows to run (default: all; 1/SR always)")
    ap.add_argument("--from-json", action="append", help="summarise rows of earlier runs instead of running")
    ap.add_argument("--figure", help="contrast-recovery curves (PNG) from the rows")
    ap.add_argument("--out", help="write the table and summary to this markdown file")
    a = ap.parse_args(argv)
    if a.speed_only:
        dt, n_el, inv, rows = speed(one_step=True)
        print(f"paper-probe 70 x 42 mm, {n_el} elements ({inv.mesh_rule}): invert() with the uncertainty "
              f"{dt:.1f} s wall")
        for (cpu, r, (c, cv)), name in zip(rows, ("two-step", "one-step")):
            print(f"{name}: {cpu:.1f} CPU s, contrast {c:.2f} (true 4), CV {100 * cv:.1f} %, beta {r.beta:.3g}, "
                  f"success {r.success}, one_step {r.one_step}")
        return rows
    sets = ["quick"] if a.quick else (a.set or ["main"])
    rows = []
    if a.from_json:
        for f in a.from_json:
            rows += json.loads(Path(f).read_text())
        sets = list(dict.fromkeys(r["set"] for r in rows))
    else:
        cost = {"L3": 0, "paper": 1, "L7": 2, "L12": 3, "L15": 4}      # cheap meshes first
        for name in sets:
            for spec in sorted(SETS[name], key=lambda sp: cost.get(sp[2], 5)):
                got = run_case(*spec, beta_study=not a.no_beta_study,
                               rows_wanted=None if not a.rows else a.rows.split(","))
                for r in got:
                    r["set"] = name
                rows += got
                r = next(x for x in got if x["row"] == "femreg")
                print(f"{r['case']}: " + ", ".join(f"{x['row']} {x['estimate']:.2f}" for x in got)
                      + f" (femreg ratio {r['ratio']:.2f}, {r['success']}, beta {r['beta']:.3g}, "
                        f"best {r.get('best_beta', np.nan):.3g}: {r.get('best_ratio', np.nan):.2f})", flush=True)
                if a.json:      # after every case: a long run can be summarised before it ends
                    Path(a.json).write_text(json.dumps(rows, default=float))
    text = table([r for r in rows if r["set"] != "curves" or r["row"] in ("femreg", "1/SR")])
    for name in sets:
        sel = [r for r in rows if r["set"] == name]
        text += "\n\n" + summary(sel, name)
        if any(r["row"] == "femreg base mesh" for r in sel):
            text += "\n" + summary(sel, f"{name}, base mesh", row="femreg base mesh")
        if name == "curves":
            continue
        out_range = [r for r in sel if not in_targets(r)]
        if out_range:
            text += "\n" + summary([r for r in sel if in_targets(r)], f"{name}, inside the targets' range")
    if a.figure:
        curves_figure(rows, a.figure)
    if not a.quick and not a.from_json and "main" in sets and not a.no_regularizers:
        text += ("\n\nStiff plane-strain disk (x4), 1 %, L7, 30 dB, registered with each regulariser:\n\n"
                 "| regulariser | model asked | model used | contrast (truth 4) | success | flags |\n"
                 "|---|---|---|---|---|---|\n")
        text += "\n".join(f"| {r} | {m} | {mu} | {c:.2f} | {ok} | {fl} |"
                          for r, m, mu, c, ok, fl in regularizer_cases())
        text += "\n"
    if not a.no_speed and not a.from_json:
        dt, n_el, inv, rows = speed(one_step=True)
        text += (f"\n- speed: paper-probe 70 x 42 mm registered pair, {n_el} elements, invert() with the beta rule "
                 f"and the uncertainty: {dt:.1f} s (success {inv.success})")
        for (cpu, r, (c, cv)), name in zip(rows, ("two-step", "one-step")):
            extra = (f", of it the one-step stage {r.one_step['cpu_seconds']:.1f} CPU s ({r.one_step['nit']} "
                     "Gauss-Newton iterations)" if r.one_step else "")
            text += (f"\n- {name}, no uncertainty: {cpu:.1f} CPU s{extra}; contrast {c:.2f} (true 4), background CV "
                     f"{100 * cv:.1f} %, success {r.success}")
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
