"""Rotated pairs: where the default registration stops being right, and whether it then says so.

In-plane rotation decorrelates speckle (the PSF stays fixed while the scatterers turn), so beyond a probe-dependent
angle no method can register a pair.  What a user needs is that femreg is right below that angle and reports
``success=False`` above it, never a wrong field with ``success=True``.  This sweep registers 1 % and 3 %
compression plus 1-4 degrees of rotation about the probe-face centre, under six probes and image sizes
(``forward.pairs.make_pair``, exact truth, seed 3), with ``femreg.register`` defaults (R_P_sigma), and prints the
total strain error, the success flag and the message.  "silent failure": total strain error above 15 % with
``success=True``.

    python benchmarks/rotation_sweep.py [--out out/rotation_sweep]

About 30 s on 2 cores.  Writes ``<out>/rotation_sweep.csv`` and ``<out>/rotation_sweep.md``.
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
import warnings
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ANGLES_DEG = (1.0, 2.0, 3.0, 4.0)
COMPRESSIONS = (0.01, 0.03)
PROBES = (("L7", (20, 20)), ("L7", (30, 30)), ("L12", (30, 30)), ("paper", (40, 30)), ("L3", (40, 40)),
          ("L15", (15, 15)))
SILENT = 0.15


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/rotation_sweep")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    import femreg
    from femreg.metrics import field_errors
    import forward.fields as F
    from forward.pairs import make_pair
    from tqdm import tqdm

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [(d, p, sz, e) for d in ANGLES_DEG for p, sz in PROBES for e in COMPRESSIONS]
    rows = []
    t0 = time.perf_counter()
    with open(out / "rotation_sweep.csv", "w", newline="") as fh:     # row by row: an interrupted run keeps its rows
        w = csv.DictWriter(fh, fieldnames=["deg", "probe", "size_mm", "compression", "e", "exx", "success",
                                           "time_s", "message"])
        w.writeheader()
        for deg, probe, size, e in tqdm(runs, desc="pairs", file=sys.stderr):
            f = F.compression_rotation(e, deg)
            p = make_pair(f, probe, size, 25, seed=3)
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
            dt = time.perf_counter() - t
            err = field_errors(r, f.displacement, f.strain)
            row = dict(deg=deg, probe=probe, size_mm=f"{size[0]}x{size[1]}", compression=e, e=float(err["e"]),
                       exx=float(err["exx"]), success=bool(r.success), time_s=dt, message=r.message)
            w.writerow(row)
            fh.flush()
            rows.append(row)
    L = ["| rotation | probe, size | 1 %: e (success) | 3 %: e (success) |", "|---|---|---|---|"]
    for deg in ANGLES_DEG:
        for probe, size in PROBES:
            cells = []
            for e in COMPRESSIONS:
                r = next(x for x in rows if x["deg"] == deg and x["probe"] == probe
                         and x["size_mm"] == f"{size[0]}x{size[1]}" and x["compression"] == e)
                flag = "" if r["success"] else " FAILED"
                mark = " **silent**" if r["success"] and r["e"] > SILENT else ""
                cells.append(f"{100 * r['e']:.1f} %{flag}{mark}")
            L.append(f"| {deg:g} deg | {probe} {size[0]} x {size[1]} mm | {cells[0]} | {cells[1]} |")
    ok = [r for r in rows if r["success"]]
    silent = [r for r in ok if r["e"] > SILENT]
    failed_good = [r for r in rows if not r["success"] and r["e"] <= 0.10]
    L += ["", f"{len(rows)} pairs: {len(ok)} with success=True (total strain error {100 * min(r['e'] for r in ok):.1f}"
              f"-{100 * max(r['e'] for r in ok):.1f} %), {len(rows) - len(ok)} failed; silent failures (e > 15 % "
              f"with success=True): {len(silent)}; flagged although within 10 %: {len(failed_good)}.  "
              f"{time.perf_counter() - t0:.0f} s."]
    md = "\n".join(L) + "\n"
    (out / "rotation_sweep.md").write_text(md)
    print(md)
    return 1 if silent else 0


if __name__ == "__main__":
    sys.exit(main())
