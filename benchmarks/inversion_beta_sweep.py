"""Fixed-beta sweeps of registered RF pairs, the data the beta rule of ``femreg.invert`` is chosen on.

For every case of a :mod:`benchmarks.inversion` set: the pair is registered (cached, as there) and inverted at each
beta of the extended grid (1 ... 1e-4, half decades) with ``uncertainty=True``.  Per beta the JSON keeps the
contrast ratio (estimate / truth), the number of parameters the data determine gamma = tr(H_d H^-1), the misfit,
and |z| = |log mu - true log mu| / sigma per constrained element with sigma *without* the registered-field factor
(``_registered_sigma``), so that a rule (a gamma target) and a calibration factor can be evaluated offline.  Per case
it keeps the element count, element size, area, and the registration's NCC.

Usage: ``python benchmarks/inversion_beta_sweep.py --set main --json sweeps_main.json`` (``--register-only``:
fill the registration cache and print nothing about the cases).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import femreg  # noqa: E402
from benchmarks import inversion as B  # noqa: E402

GRID = tuple(float(10.0 ** e) for e in np.arange(0.0, -4.01, -0.5))


def sweep_case(model, contrast, probe, snr, radius=5.0, level=0.01, seed=0):
    case = B.case_name(model, contrast, probe, snr, radius, level, seed)
    field = B.truth_field(model, contrast, level, radius)
    reg, _ = B.register(case, field, probe, snr, seed)
    ext = reg.mesh.p[:, reg.mesh.t].max(axis=1) - reg.mesh.p[:, reg.mesh.t].min(axis=1)
    out = dict(case=case, model=model, contrast=contrast, probe=probe, snr=snr, radius=radius, level=level,
               seed=seed, n_el=int(reg.mesh.t.shape[1]), h=[float(np.median(ext[0])), float(np.median(ext[1]))],
               ncc_after=float(reg.ncc_after), quality=float(np.nanmedian(reg.quality)) if reg.quality is not None
               else float("nan"), sweep=[])
    for b in GRID:
        t = time.process_time()
        inv = femreg.invert(reg, beta_grid=[b])
        cest, cv = B.sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)
        c = inv.centroids
        true = np.where(field.inside(c), np.log(contrast), 0.0)
        ok = inv.constrained & np.isfinite(inv.uncertainty)
        z = np.abs(np.log(inv.mu[ok]) - true[ok]) / (inv.uncertainty[ok] / femreg.inversion._registered_sigma(
            float(np.sqrt(np.mean(np.prod(np.ptp(inv.mesh.p[:, inv.mesh.t], axis=1), axis=0))))))
        out["area"] = float(np.ptp(inv.mesh.p[0]) * np.ptp(inv.mesh.p[1]))
        out["sweep"].append(dict(beta=b, ratio=cest / contrast, cv=cv, gamma=inv.sweep[0]["gamma"],
                                 misfit=inv.misfit, misfit_model=inv.misfit_model_strain, ok=bool(inv.success),
                                 flags="; ".join(inv.flags)[:80], z=np.round(z, 3).tolist(),
                                 cpu=time.process_time() - t))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", choices=tuple(B.SETS), required=True)
    ap.add_argument("--json")
    ap.add_argument("--register-only", action="store_true")
    a = ap.parse_args(argv)
    cost = {"L3": 0, "paper": 1, "L7": 2, "L12": 3, "L15": 4}
    rows = []
    for name in a.set:
        for spec in sorted(B.SETS[name], key=lambda sp: cost.get(sp[2], 5)):
            t = time.process_time()
            if a.register_only:
                case = B.case_name(*spec)
                B.register(case, B.truth_field(spec[0], spec[1], spec[5], spec[4]), spec[2], spec[3], spec[6])
                print(f"registered {case}: {time.process_time() - t:.0f} s CPU", flush=True)
                continue
            r = sweep_case(*spec)
            r["set"] = name
            rows.append(r)
            print(f"{r['case']}: n_el {r['n_el']}, " + ", ".join(
                f"{e['beta']:.3g}:{e['ratio']:.2f}/{e['gamma']:.0f}" for e in r["sweep"])
                + f" ({time.process_time() - t:.0f} s CPU)", flush=True)
            if a.json:
                Path(a.json).write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
