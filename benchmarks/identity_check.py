"""Bit-identity check of registrations across a refactoring: register a few diverse pairs, store every output
array, and compare a later run against the stored one with ``np.array_equal`` (NaN equal to NaN).

Cases: simulated pairs from :mod:`forward.pairs` (robustness-benchmark fields: 1 % compression with R_P_sigma,
shear with R_eps, also with alpha="auto", bending with R_P_eps, 2 degree rotation; 1 and 3 degree rotations whose
peak hopping is repaired / remains), 5 % compression with ``strategy="paper"`` (block matching and the coarse
pass), the in vivo pair seq304 frames 1 -> 3 on the demo's crop, by default and with the paper's procedure
(skipped when the data are absent), a 4-frame ``track`` and an inversion of the first result.  Also writes each
pair's result file (``--files``) so that a later version can be checked to load it (``--load``).

    python benchmarks/identity_check.py --save out/identity/base.npz
    python benchmarks/identity_check.py --compare out/identity/base.npz
    python benchmarks/identity_check.py --robustness ...   # also every robustness case x 5 femreg methods and
                                                           # the whole in vivo frames 1 -> 6 x 4 regularisers
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import femreg  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import make_pair, make_sequence  # noqa: E402

INVIVO = ROOT.parent / "shared" / "data" / "invivo_rf" / "seq304"
if not INVIVO.is_dir():
    INVIVO = Path("/work/shared/data/invivo_rf/seq304")


def _result_arrays(prefix, res, out):
    """Every output of a RegistrationResult as named arrays."""
    out[prefix + "u"] = res.u
    out[prefix + "p"] = res.mesh.p
    for mode in ("recovered", "element"):
        for k, v in res.on_grid(mode).items():
            out[f"{prefix}grid_{mode}_{k}"] = v
    rng = np.random.default_rng(0)
    lo, hi = res.mesh.p.min(axis=1), res.mesh.p.max(axis=1)
    pts = lo + (hi - lo) * rng.uniform(-0.05, 1.05, size=(200, 2))
    out[prefix + "disp_pts"] = res.displacement(pts)
    out[prefix + "strain_rec_pts"] = res.strain(pts)
    out[prefix + "strain_el_pts"] = res.strain(pts, strain="element")
    out[prefix + "scalars"] = np.array([res.success, res.status, res.nit, res.ncc_before, res.ncc_after,
                                        res.alpha, res.alpha_effective], float)
    out[prefix + "energy_history"] = res.energy_history
    out[prefix + "quality"] = np.array([]) if res.quality is None else res.quality
    out[prefix + "hop_gain"] = np.array([]) if res.hop_gain is None else res.hop_gain
    out[prefix + "message"] = np.array(res.message)


def run_robustness(arrays, times):
    """Every case of the robustness benchmark (benchmarks/robustness.py) with femreg's five methods."""
    from benchmarks.robustness import CASES, FEMREG_METHODS, make_data

    for case in CASES:
        data = make_data(case)
        for method, reg in list(FEMREG_METHODS.items()) + [("R_P_sigma_paper", "momentum-stress")]:
            kw = dict(spacing=data.spacing, origin=data.origin, regularizer=reg)
            if method.endswith("paper"):
                kw["strategy"] = "paper"
            t = time.perf_counter()
            if case.sequence:
                res = femreg.track(data.frames, **kw)
                res = res[-1]
            else:
                res = femreg.register(data.ref, data.mov, **kw)
            key = f"robust/{case.name}/{method}/"
            times[key] = time.perf_counter() - t
            arrays[key + "u"] = res.u
            arrays[key + "message"] = np.array(res.message)
            for k, v in res.on_grid().items():
                arrays[key + k] = v


def run_invivo_full(arrays, times):
    """Both in vivo sequences, whole frames 1 -> 6, with the four regularisers (default settings)."""
    from femreg.io import read_frames

    for seq in ("seq299", "seq304"):
        folder = INVIVO.parent / seq
        if not folder.is_dir():
            continue
        fr = read_frames(folder, shape=(2000, 128), spacing=(0.02, 0.2))
        frames = np.asarray(fr.frames, float)
        for reg in ("strain", "strain-incompressible", "momentum-strain", "momentum-stress"):
            t = time.perf_counter()
            res = femreg.register(frames[0], frames[5], spacing=fr.spacing, origin=fr.origin, regularizer=reg)
            key = f"invivo_full/{seq}/{reg}/"
            times["robust/" + key] = time.perf_counter() - t
            arrays[key + "u"] = res.u
            arrays[key + "scalars"] = np.array([res.success, res.ncc_before, res.ncc_after, res.nit], float)
            arrays[key + "exx"] = res.on_grid()["exx"]


def run(outdir: Path | None, robustness: bool = False):
    arrays, times = {}, {}
    if robustness:
        run_robustness(arrays, times)
        run_invivo_full(arrays, times)
    pairs = {
        "comp1_Rps": (make_pair(F.compression(0.01), "paper", (40, 30), 20, seed=0), {}),
        "shear_Reps": (make_pair(F.shear_rotation(0.01), "L7", (30, 30), 30, seed=0), {"regularizer": "strain"}),
        "bend_RPe": (make_pair(F.Bending(0.002, 0.02, 40.0), "paper", (40, 40), 25, seed=0),
                     {"regularizer": "momentum-strain"}),
        "rot2_Rps": (make_pair(F.shear_rotation(0.01, shear=0.0, rotation_deg=2.0), "L12", (30, 30), 25, seed=0),
                     {}),
        "rot1_L3_repair": (make_pair(F.compression_rotation(0.01, 1.0), "L3", (40, 40), 25, seed=3), {}),
        "rot3_paper_hops": (make_pair(F.compression_rotation(0.01, 3.0), "paper", (40, 30), 25, seed=3), {}),
        "comp5_paper": (make_pair(F.compression(0.05), "paper", (40, 30), 25, seed=0), {"strategy": "paper"}),
    }
    pairs["shear_auto_alpha"] = (pairs["shear_Reps"][0], {"regularizer": "strain", "alpha": "auto"})
    results = {}
    for name, (pair, kw) in pairs.items():
        t = time.perf_counter()
        res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, **kw)
        times[name] = time.perf_counter() - t
        results[name] = res
        _result_arrays(name + "/", res, arrays)
    if INVIVO.is_dir():
        from femreg.io import read_frames

        fr = read_frames(INVIVO, shape=(2000, 128), spacing=(0.02, 0.2))
        frames = np.asarray(fr.frames, float)[:, 550:1150, 0:64]
        sp = tuple(float(s) for s in fr.spacing)
        org = (float(fr.origin[0]) + 550 * sp[0], float(fr.origin[1]))
        t = time.perf_counter()
        res = femreg.register(frames[0], frames[2], spacing=sp, origin=org)
        times["invivo304"] = time.perf_counter() - t
        results["invivo304"] = res
        _result_arrays("invivo304/", res, arrays)
        t = time.perf_counter()
        res = femreg.register(frames[0], frames[2], spacing=sp, origin=org, strategy="paper",
                              regularizer="strain", element_size=(1.0, 1.0), margin=(0.5, 0.6))
        times["invivo304_paper"] = time.perf_counter() - t
        _result_arrays("invivo304_paper/", res, arrays)
    seq = make_sequence(F.compression(0.01), "L7", (20, 20), 30, seed=0, n_frames=4)
    t = time.perf_counter()
    tr = femreg.track(seq.frames, spacing=seq.spacing, origin=seq.origin)
    times["track4"] = time.perf_counter() - t
    for k, r in enumerate(tr):
        _result_arrays(f"track4/{k}/", r, arrays)
    arrays["track4/flags"] = np.array([str(f) for f in getattr(tr, "flags", [])])
    t = time.perf_counter()
    inv = femreg.invert(results["comp1_Rps"], beta=1e-3)
    times["invert"] = time.perf_counter() - t
    for k, v in vars(inv).items():
        if isinstance(v, np.ndarray) and v.dtype != object:
            arrays["invert/" + k] = v
        elif isinstance(v, (int, float, bool, str)):
            arrays["invert/" + k] = np.array(v)
    if outdir is not None:
        outdir.mkdir(parents=True, exist_ok=True)
        for name, res in results.items():
            res.save(outdir / f"{name}.npz")
        inv.save(outdir / "invert.npz") if hasattr(inv, "save") else None
    return arrays, times


def compare(a: dict, b) -> list:
    bad = []
    for k in sorted(set(a) | set(b.files)):
        if k not in a or k not in b.files:
            bad.append(f"{k}: missing on one side")
            continue
        x, y = np.asarray(a[k]), b[k]
        if x.dtype.kind in "fc" and y.dtype.kind in "fc":
            same = x.shape == y.shape and np.array_equal(x, y, equal_nan=True)
        else:
            same = x.shape == y.shape and np.array_equal(x, y)
        if not same:
            d = ""
            if x.shape == y.shape and x.dtype.kind in "fc":
                d = f" max |diff| {np.nanmax(np.abs(x - y)) if x.size else 0:.3g}"
            bad.append(f"{k}: differs{d}")
    return bad


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--save", type=Path)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--files", type=Path, help="folder for the result files written by this version")
    ap.add_argument("--load", type=Path, help="folder of result files of an earlier version: check they load")
    ap.add_argument("--robustness", action="store_true", help="also every robustness-benchmark case x femreg method")
    ap.add_argument("--no-compiled", action="store_true", help="without the numba loops (femreg._kernels)")
    args = ap.parse_args(argv)
    if args.no_compiled:
        from femreg import _kernels

        _kernels.HAVE_NUMBA = False
    arrays, times = run(args.files, args.robustness)
    for k, v in times.items():
        if not k.startswith("robust/"):
            print(f"{k:18s} {v:7.3f} s")
    robust = [v for k, v in times.items() if k.startswith("robust/")]
    if robust:
        print(f"robustness: {len(robust)} registrations / tracks in {sum(robust):.1f} s")
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        np.savez(args.save, **{k: np.asarray(v) for k, v in arrays.items()})
        print(f"saved {len(arrays)} arrays to {args.save}")
    rc = 0
    if args.compare:
        bad = compare(arrays, np.load(args.compare))
        print(f"compared {len(arrays)} arrays: " + ("all bit-identical" if not bad else f"{len(bad)} differ"))
        for line in bad[:40]:
            print("  " + line)
        rc = 1 if bad else 0
    if args.load:
        for p in sorted(args.load.glob("*.npz")):
            if p.stem == "invert":
                femreg.load_inversion(p) if hasattr(femreg, "load_inversion") else None
                continue
            r = femreg.load_result(p)
            g = r.on_grid()
            assert np.array_equal(r.u, np.load(p)["u"]), p
            print(f"loaded {p.name}: {len(r.u)} dofs, grid {g['exx'].shape}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
