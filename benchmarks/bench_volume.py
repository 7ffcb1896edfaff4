"""Benchmark of volume registration (``femreg.register`` on RF volumes): a 20 x 20 x 15 mm pair of 800 x 100 x 60
voxels (dx 0.025, dy 0.2, dz 0.25 mm) related by an exact affine field (1 % compression with half of it as
lateral and elevational expansion, 0.5 % shear e_xy, 0.5 degree rotation about z), simulated with the separable
PSF of tests/_volumes.py (point scatterers, Gaussian-modulated pulse, Gaussian beams).

Prints the wall and CPU time of the whole ``register`` call and of its stages, its peak memory (the registration
runs in a fresh process, so ru_maxrss is its own), and the total strain error over the six components (shear
counted twice) over the interior (2 mm margin) against the exact field, and the fraction of elements the
peak-hopping check (:func:`femreg.repair.envelope_lag_ncc_3d`) flags, per probe frequency.

    python benchmarks/bench_volume.py                       # 7 MHz, default settings
    python benchmarks/bench_volume.py --probes 3 7.5 15     # accuracy per probe
    python benchmarks/bench_volume.py --shape 400 50 30     # a smaller volume
    python benchmarks/bench_volume.py --refine auto         # with adaptive refinement (femreg.volume_refine)
    python benchmarks/bench_volume.py --refine interior=1,max_growth=8   # VOLUME_REFINEMENT with these fields
    python benchmarks/bench_volume.py --element-size 2 2.4 2 --refine plane   # PLANE_REFINEMENT at the central plane
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

SPACING = (0.025, 0.2, 0.25)
WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])


def axial_spacing(f_mhz) -> float:
    """dx (mm) of a probe: 0.025 mm (fs 30.8 MHz), finer where that leaves fewer than 4 samples per carrier
    period (RF sampled at >= 4 f0, as scanners do; at 15 MHz 0.025 mm would alias the pulse)."""
    return min(SPACING[0], 1.54 / (2 * 4 * f_mhz))


def _pair(shape, f_mhz, seed, density, cache):
    from _volumes import affine_field, volume_pair

    spacing = (axial_spacing(f_mhz),) + SPACING[1:]
    shape = (int(round(shape[0] * SPACING[0] / spacing[0])),) + tuple(shape[1:])     # the same extent
    path = Path(cache) / f"volpair_{'x'.join(map(str, shape))}_{f_mhz:g}_{seed}_{density:g}.npz"
    field, G = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * spacing / 2)
    if path.exists():
        with np.load(path) as z:
            stale = not {"ref", "mov", "spacing"} <= set(z.files)     # written by an older version of this script
    if not path.exists() or stale:
        t = time.perf_counter()
        ref, mov, _, _ = volume_pair(field, shape=shape, spacing=spacing, f_mhz=f_mhz, seed=seed, density=density)
        np.savez(path, ref=ref.astype(np.float32), mov=mov.astype(np.float32), spacing=np.asarray(spacing))
        print(f"  simulated in {time.perf_counter() - t:.1f} s -> {path}", flush=True)
    return path, G


def _register_child(path, G, options):
    """Runs in a fresh process: register, time, error, peak memory; prints one JSON line."""
    import femreg
    from femreg.repair import hopped_fraction

    z = np.load(path)
    ref, mov, spacing = z["ref"], z["mov"], tuple(z["spacing"])
    if options.get("refine") == "plane":
        # femreg.volume_refine.PLANE_REFINEMENT at the voxel plane nearest the volume's elevational centre
        import dataclasses

        from femreg.volume_refine import PLANE_REFINEMENT
        options["refine"] = dataclasses.replace(PLANE_REFINEMENT, plane=0.5 * (ref.shape[2] - 1) * spacing[2])
    if isinstance(options.get("refine"), str) and "=" in options["refine"]:
        import dataclasses

        from femreg.volume_refine import VOLUME_REFINEMENT
        kw = dict(kv.split("=", 1) for kv in options["refine"].split(","))
        options["refine"] = dataclasses.replace(VOLUME_REFINEMENT, **{k: float(v) if "." in v else int(v)
                                                                      for k, v in kw.items()})
    t0, c0 = time.perf_counter(), time.process_time()
    res = femreg.register(ref, mov, spacing=spacing, **options)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    E = 0.5 * (G + G.T)
    truth = np.array([E[0, 0], E[1, 1], E[2, 2], E[0, 1], E[0, 2], E[1, 2]])
    pts = res.voxel_points()
    ext = np.asarray(res.shape) * np.asarray(spacing)
    m = np.all((pts > 2.0) & (pts < ext - 2.0), axis=1)
    e = res.strain(pts[m][::7])
    err = float(np.sqrt(np.nanmean(np.sum(WEIGHTS * (e - truth) ** 2, axis=1)) / np.sum(WEIGHTS * truth ** 2)))
    comp = np.sqrt(np.nanmean((e - truth) ** 2, axis=0))
    print(json.dumps({"shape": list(res.shape), "wall": wall, "cpu": cpu, "error": err, "rms_per_component": comp.tolist(),
                      "hopped": hopped_fraction(res.hop_gain), "max_hop_gain": float(np.nanmax(res.hop_gain)),
                      "success": res.success, "message": res.message, "nit": res.nit,
                      "n_nodes": int(res.mesh.p.shape[1]), "timings": {k: v for k, v in res.timings.items()},
                      "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--probes", type=float, nargs="+", default=[7.0], help="centre frequencies, MHz")
    ap.add_argument("--shape", type=int, nargs=3, default=[800, 100, 60])
    ap.add_argument("--density", type=float, default=40.0, help="scatterers per mm^3")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--element-size", type=float, nargs="+", default=None, help="mm: one size, or axial, "
                    "lateral, elevational")
    ap.add_argument("--regularizer", default="momentum-stress")
    ap.add_argument("--refine", default=None, help="refine= of the registration: 'auto', a number of passes, "
                    "'key=value,...' (femreg.volume_refine.VOLUME_REFINEMENT with those numeric fields) or 'plane' "
                    "(femreg.volume_refine.PLANE_REFINEMENT at the central plane)")
    ap.add_argument("--cache", default=os.environ.get("FEMREG_CACHE", tempfile.gettempdir()))
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        _register_child(a.child[0], np.array(json.loads(a.child[1])), json.loads(a.child[2]))
        return
    opts = {"regularizer": a.regularizer}
    if a.element_size is not None:
        opts["element_size"] = a.element_size[0] if len(a.element_size) == 1 else a.element_size
    if a.refine is not None:
        opts["refine"] = int(a.refine) if a.refine.isdigit() else a.refine
    shape = tuple(a.shape)
    ext = np.array(shape) * SPACING
    print(f"volume {shape[0]} x {shape[1]} x {shape[2]} voxels = {ext[0]:g} x {ext[1]:g} x {ext[2]:g} mm, "
          f"{a.regularizer}", flush=True)
    for f in a.probes:
        path, G = _pair(shape, f, a.seed, a.density, a.cache)
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        out = subprocess.run([sys.executable, __file__, "--child", str(path), json.dumps(G.tolist()),
                              json.dumps(opts)], capture_output=True, text=True, env=env)
        if out.returncode != 0:
            print(out.stderr)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        st = ", ".join(f"{k} {v:.2f}" for k, v in r["timings"].items() if isinstance(v, float))
        print(f"{f:5.1f} MHz (dx {axial_spacing(f):.4f} mm): wall {r['wall']:.1f} s, CPU {r['cpu']:.1f} s, peak {r['maxrss_mb']:.0f} MB, "
              f"total strain error {100 * r['error']:.2f} % (RMS per component "
              f"{', '.join(f'{v:.1e}' for v in r['rms_per_component'])}), {r['nit']} iterations, "
              f"{r['n_nodes']} nodes, hopped {100 * r['hopped']:.1f} % of the elements (largest gain "
              f"{r['max_hop_gain']:.2f}), success {r['success']}\n        stages: {st}", flush=True)


if __name__ == "__main__":
    main()
