"""3D modulus inversion (``femreg.invert`` on hexahedra) of the paper's 3D phantom displacements.

Truth: the paper's 3D FE model (``forward.elasticity.cached_solve("3d", ...)``: 160 mm cube, 15 mm sphere at
30 mm depth, 50 mm patch, 1 mm compression, nu = 0.495, P2 tetrahedra; HI / mHI / SI / HOM = sphere 40 / 20 / 5 /
10 MPa in 10 MPa, i.e. shear-modulus contrast 4 / 2 / 0.5 / 1), its exact displacement
(``Solution.displacement_3d``) sampled at the nodes of a hexahedral mesh.  Regions:

- ``sphere``: 30 x 30 mm around the sphere in the imaging plane (x 15-45 mm, y +-15 mm), z +-10 mm;
- ``imaged``: the paper's imaged area (x 2-70 mm, y +-22 mm), z +-10 mm.

Rows: exact displacement; the same with seeded white Gaussian noise added at the nodes, sigma = 1 um axial and
5 um lateral / elevational (the order of a registration's errors at this strain: mean axial strain ~0.6 %);
fixed beta (default 1e-3) unless ``--rule`` (femreg's beta rule).  Contrast: :func:`femreg.inversion.
modulus_contrast` (elements fully inside / fully outside the sphere, volume-weighted means), as the 2D inversion
of the same data is scored (plane stress of the exact 3D displacement: 2.2).  Time: the whole ``invert`` call;
memory: the process' peak RSS after the case (monotone over the run).

``--elevation``: the effect of the poorly measured elevational component, HI with sigma_z = 5 / 20 / 50 um and
elevational misfit weight 0.1 / 0.01.

``--correlated``: registration-like noise, correlated over a few mm (per component a sum of 24 plane waves of
random direction, phase and wavelength in 3-6 mm, or 6-12 mm; seeded), at several levels, inverted with femreg's
defaults (3D: lateral and elevational boundary values fitted, misfit weights from the data's noise) and with the
former ones (all boundary values imposed, weights 1 / 0.1 / 0.1).

``--one-step``: two-step against one-step inversion (``femreg.invert(result, reference_image=, moving_image=)``)
on *registered* RF volumes of the phantom (``forward.volume.paper_volume_sequence``, frames 1 -> 7, cached; the
volumes and crops of benchmarks/volume_study.py), registered with femreg's defaults (2 mm elements) and inverted
on the registration's own mesh and over the sphere's box (clipped to the crop less 2 mm) with 2 mm elements, beta
``--beta`` (or the rule with ``--rule``); contrast and background CV as above, CPU seconds (``time.process_time``)
of each ``invert`` call, of the one-step stage alone, and the peak RSS.  ``--crops quick,full`` (quick: x 20-42,
y +-11, z +-5 mm; full: the whole volume), ``--cases HI`` (other inclusions render their volumes first).

Usage: ``python benchmarks/inversion3d.py [--quick] [--rule] [--h 2] [--cases HI,SI,mHI,HOM] [--regions
sphere,imaged] [--elevation] [--correlated] [--one-step [--crops quick,full]]``.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import femreg  # noqa: E402
from femreg.inversion import modulus_contrast  # noqa: E402
from forward.elasticity import cached_solve  # noqa: E402

MODULI = {"HI": 40.0, "mHI": 20.0, "SI": 5.0, "HOM": 10.0}
BACKGROUND = 10.0
REGIONS = {"sphere": (15.0, 45.0, -15.0, 15.0, -10.0, 10.0), "imaged": (2.0, 70.0, -22.0, 22.0, -10.0, 10.0)}
#: Noise of the "noisy" rows, mm (axial, lateral, elevational).
NOISE_MM = (1e-3, 5e-3, 5e-3)


def sphere(points):
    p = np.asarray(points, float)
    return (p[:, 0] - 30.0) ** 2 + p[:, 1] ** 2 + p[:, 2] ** 2 < 7.5 ** 2


def truth(case):
    return cached_solve("3d", inclusion_modulus=MODULI[case], background_modulus=BACKGROUND,
                        inclusion_depth_mm=30.0, inclusion_diameter_mm=15.0, compression_mm=1.0)


def noisy(fun, sigma, seed=0):
    """``fun`` plus white Gaussian noise (n, 3) of standard deviations ``sigma`` (mm), seeded per call size."""
    def f(p):
        v = fun(p)
        rng = np.random.default_rng([seed, len(p)])
        return v + rng.standard_normal(v.shape) * np.asarray(sigma, float)
    return f


def smooth_noise(sigma, seed=0, n_modes=24, wavelength_mm=(3.0, 6.0)):
    """A registration-like error field (n, 3) -> (n, 3) mm: per component a sum of ``n_modes`` plane waves of
    random direction, phase and wavelength, standard deviation ``sigma`` (3,) mm (tests/test_inversion3d.py)."""
    rng = np.random.default_rng(seed)
    k = rng.standard_normal((3, n_modes, 3))
    k *= 2 * np.pi / rng.uniform(*wavelength_mm, (3, n_modes, 1)) / np.linalg.norm(k, axis=2, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, (3, n_modes))
    sig = np.asarray(sigma, float)
    return lambda p: np.column_stack([sig[c] * np.sqrt(2.0 / n_modes) * np.cos(p @ k[c].T + phase[c]).sum(axis=1)
                                      for c in range(3)])


#: Former 3D defaults (all boundary values imposed, weights 1 / 0.1 / 0.1), the "before" rows of --correlated.
FORMER = dict(boundary="measured", weights=(1.0, 0.1, 0.1))


def run(case, region, h, beta, noise=False, uncertainty=True, sigma=NOISE_MM, weights=None, noise_fun=None,
        **kw):
    sol = truth(case)
    fun = noisy(sol.displacement_3d, sigma) if noise else sol.displacement_3d
    if noise_fun is not None:
        fun = (lambda f, n: (lambda p: f(p) + n(p)))(sol.displacement_3d, noise_fun)
    t = time.perf_counter()
    kw = dict(kw) if weights is None else dict(kw, weights=weights)
    inv = femreg.invert(fun, region=REGIONS[region], element_size=h, beta=beta, uncertainty=uncertainty, **kw)
    dt = time.perf_counter() - t
    true = MODULI[case] / BACKGROUND
    row = dict(case=case, region=region, h=h, noise=noise, beta=inv.beta, n_el=inv.mu.size,
               dofs=3 * inv.mesh.p.shape[1], seconds=dt, nit=inv.nit, n_eval=inv.timings.get("n_evaluations"),
               t_unc=inv.timings.get("uncertainty"), rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
               success=inv.success, flags="; ".join(inv.flags)[:80], true=true, weights=inv.weights)
    if case == "HOM":
        row.update(contrast=float("nan"), cv=float(np.std(inv.mu) / np.mean(inv.mu)))
    else:
        m = modulus_contrast(inv, sphere)
        row.update(contrast=m["contrast"], cv=m["cv_background"])
    if inv.uncertainty is not None:
        row["median_std"] = float(np.nanmedian(inv.uncertainty))
    return row


CROPS = {"quick": (20.0, 42.0, -11.0, 11.0, -5.0, 5.0), "full": None}


def one_step_rows(case, crop_name, beta):
    """Registered volumes of ``case`` cropped to ``crop_name``: two-step and one-step inversions (rows)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from volume_study import crop, in_sphere, inversion_region  # noqa: E402
    from forward.volume import paper_volume_sequence  # noqa: E402

    seq = paper_volume_sequence(case, frames=(0, 6))
    sl, origin = crop(seq, CROPS[crop_name])
    ref, mov = (np.asarray(seq.frames[i][sl], np.float64) for i in (0, 1))
    c0 = time.process_time()
    reg = femreg.register(ref, mov, spacing=seq.spacing, origin=origin)
    t_reg = time.process_time() - c0
    region = inversion_region(seq, sl)
    true = MODULI[case] / BACKGROUND
    rows = []
    for where, kw in (("mesh", {}), ("sphere box", dict(region=region, element_size=2.0))):
        for name, img in (("two-step", {}), ("one-step", dict(reference_image=ref, moving_image=mov))):
            c0 = time.process_time()
            inv = femreg.invert(reg, beta=beta, uncertainty=False, **kw, **img)
            cpu = time.process_time() - c0
            m = modulus_contrast(inv, in_sphere) if case != "HOM" else None
            rows.append(dict(case=case, crop=crop_name, shape=ref.shape, where=where, inversion=name,
                             n_el=inv.mu.size, dofs=3 * inv.mesh.p.shape[1], beta=inv.beta,
                             contrast=m["contrast"] if m else float("nan"), true=true,
                             cv=m["cv_background"] if m else float(np.std(inv.mu) / np.mean(inv.mu)),
                             cpu=cpu, cpu_one_step=(inv.one_step or {}).get("cpu_seconds", float("nan")),
                             nit=(inv.one_step or {}).get("nit", 0), cg=(inv.one_step or {}).get("cg_iterations", 0),
                             psi=(inv.one_step or {}).get("psi_two_step", float("nan")),
                             psi1=(inv.one_step or {}).get("psi_one_step", float("nan")), success=inv.success,
                             flags="; ".join(inv.flags)[:80], t_reg=t_reg,
                             rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
            r = rows[-1]
            print(f"| {case} | {crop_name} {'x'.join(map(str, r['shape']))} | {where} | {name} | {r['n_el']} / "
                  f"{r['dofs']} | {r['beta']:.3g} | {r['contrast']:.3f} ({true:g}) | "
                  f"{abs(r['contrast'] / true - 1) * 100:.1f} % | {100 * r['cv']:.1f} % | {r['cpu']:.1f} | "
                  f"{r['cpu_one_step']:.1f} | {r['nit']} / {r['cg']} | {r['psi']:.4g} -> {r['psi1']:.4g} | "
                  f"{r['rss_mb']:.0f} | {r['success']} | {r['flags']} |", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="HI only, sphere region, 3 mm elements")
    ap.add_argument("--rule", action="store_true", help="beta by femreg's rule instead of --beta")
    ap.add_argument("--beta", type=float, default=1e-3)
    ap.add_argument("--h", type=float, default=2.0, help="element size, mm")
    ap.add_argument("--cases", default="HI,SI,mHI,HOM")
    ap.add_argument("--regions", default="sphere")
    ap.add_argument("--noise", default="HI", help="cases also run with noise added (comma-separated)")
    ap.add_argument("--no-uncertainty", action="store_true")
    ap.add_argument("--correlated", action="store_true",
                    help="only the correlated-noise study: HI, defaults against the former 3D defaults")
    ap.add_argument("--elevation", action="store_true",
                    help="only the elevational-noise study: HI, sigma_z 5 / 20 / 50 um, w_z 0.1 and 0.01")
    ap.add_argument("--one-step", action="store_true",
                    help="only two-step against one-step inversion of registered RF volumes (--crops, --cases)")
    ap.add_argument("--crops", default="quick", help="with --one-step: quick,full")
    a = ap.parse_args(argv)
    if a.one_step:
        print("| case | crop (voxels) | inverted on | inversion | elements / DOFs | beta | contrast (true) | "
              "error | CV bg | CPU s | one-step CPU s | GN it / CG it | image term | peak RSS MB | success | flags |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        rows = []
        for case in a.cases.split(","):
            for crop_name in a.crops.split(","):
                rows += one_step_rows(case, crop_name, None if a.rule else a.beta)
        return rows
    cases = ["HI"] if a.quick else a.cases.split(",")
    h = 3.0 if a.quick else a.h
    beta = None if a.rule else a.beta
    rows = []
    if a.correlated:
        print("| sigma (axial / lateral / elevational) um | wavelength mm | inversion | contrast HI (4) | CV bg | "
              "weights | seconds |")
        print("|---|---|---|---|---|---|---|")
        for sig, wl in (((1, 5, 5), (3, 6)), ((1, 5, 20), (3, 6)), ((1, 5, 50), (3, 6)), ((2, 10, 20), (3, 6)),
                        ((1, 5, 20), (6, 12)), ((1, 5, 50), (6, 12))):
            nf = smooth_noise(1e-3 * np.asarray(sig, float), seed=0, wavelength_mm=wl)
            for name, kw in (("former", FORMER), ("default", {})):
                r = run("HI", a.regions.split(",")[0], h, beta, uncertainty=False, noise_fun=nf, **kw)
                print(f"| {' / '.join(map(str, sig))} | {wl[0]}-{wl[1]} | {name} | {r['contrast']:.3f} | "
                      f"{100 * r['cv']:.1f} % | {' / '.join(f'{v:.3g}' for v in r['weights'])} | "
                      f"{r['seconds']:.1f} |", flush=True)
                rows.append(r)
        return rows
    if a.elevation:
        print("| sigma (axial, lateral, elevational) um | weights | contrast HI (4) | CV bg | seconds |")
        print("|---|---|---|---|---|")
        for sz in (5e-3, 20e-3, 50e-3):
            for w in ((1.0, 0.1, 0.1), (1.0, 0.1, 0.01)):
                r = run("HI", a.regions.split(",")[0], h, beta, True, uncertainty=False, sigma=(1e-3, 5e-3, sz),
                        weights=w)
                print(f"| 1 / 5 / {1e3 * sz:g} | {w} | {r['contrast']:.3f} | {100 * r['cv']:.1f} % | "
                      f"{r['seconds']:.1f} |", flush=True)
                rows.append(r)
        return rows
    print("| case | region | h mm | noise | elements | DOFs | beta | contrast (true) | ratio | CV bg | median "
          "std log mu | seconds | L-BFGS it / evals | uncertainty s | peak RSS MB | success | flags |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for region in a.regions.split(","):
        for case in cases:
            for noise in ((False, True) if case in a.noise.split(",") else (False,)):
                r = run(case, region, h, beta, noise, uncertainty=not a.no_uncertainty)
                rows.append(r)
                ratio = r["contrast"] / r["true"] if np.isfinite(r["contrast"]) else float("nan")
                print(f"| {case} | {region} | {h:g} | {'1/5/5 um' if noise else '-'} | {r['n_el']} | {r['dofs']} | "
                      f"{r['beta']:.3g} | {r['contrast']:.3f} ({r['true']:g}) | {ratio:.3f} | "
                      f"{100 * r['cv']:.1f} % | {r.get('median_std', float('nan')):.3g} | {r['seconds']:.1f} | "
                      f"{r['nit']} / {r['n_eval']} | {r['t_unc']:.1f} | {r['rss_mb']:.0f} | {r['success']} | "
                      f"{r['flags']} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
