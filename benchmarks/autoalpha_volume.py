"""``alpha="auto"`` on RF volumes: the automatic alpha against the default one and the truth-best one of the same
grid, on small simulated volumes.

Every case is a 10 x 8 x 6 mm volume pair (``forward.volume.make_volume_pair``: point scatterers, the probe's
separable PSF, white noise at ``snr_db``) related by an exact field: affine compression (0.5, 2, 5 %, with the
incompressible lateral and elevational expansion), compression with shear e_xy and a rotation, or the paper's
stiff sphere (the 3D FE solution of the HI phantom, 4x stiffer, 15 mm across, scaled to 1 or 2 % mean axial
strain over the volume, which holds the upper part of the sphere), imaged with three probes: 3.5 MHz
(``swept3``), 7 MHz (``matrix7``) and 15 MHz (a matrix array at 0.1 / 0.2 mm pitch).

For each case :func:`femreg.autoalpha.choose_alpha` runs its grid (the default alpha x 10^(-1.5 ... 1.5), half
decades; the volume registration and image term of ``femreg.register(..., alpha="auto")``) with
``keep_results=True``, and ``femreg.register`` runs once more at the default alpha (what a user gets without
``alpha``).  Every registration is scored with the volume benchmarks' metric: the six-component total strain
error (shear counted twice, relative L2) over the interior voxels (2 mm from the volume's faces) against the exact
field (:func:`volume_study.volume_errors_3d`).  Reported: how often the automatic alpha's error is within 15 % of
the truth-best grid alpha's, within 0.5 percentage points, or either; the same for the default alpha; and the CPU
time of ``alpha="auto"`` against one registration at the default alpha.

Two seed sets: ``--set A`` (seeds 0 ...) on which the rule may be looked at, ``--set B`` (seeds 1000 ...), the
held-out set, fixed before any result of set A was seen.

    python benchmarks/autoalpha_volume.py --set A [--cases sphere,comp] [--probes 7MHz] [--regularizer strain]
                                          [--out out/autoalpha_volume]

Writes ``<out>/<set>.csv`` (one row per case, the whole error curve) and ``<out>/<set>.md`` (``<set>_<regulariser>``
for another regulariser than the default).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from autoalpha import write_row  # noqa: E402

WITHIN, POINTS = 1.15, 0.5
SIZE_MM = (10.0, 8.0, 6.0)
#: Depth of the volume's top, mm: it spans x 18-28 mm, the sphere (centre 30 mm, radius 7.5 mm) fills its lower part.
TOP_MM = 18.0
SEED_BASE = {"A": 0, "B": 1000}


def probes():
    from forward.volume import VOLUME_PROBES, VolumeProbe

    # 15 MHz: 0.1 mm lateral pitch, 0.2 mm elevational, fs 60 MHz (dx 0.0128 mm)
    p15 = VolumeProbe(15.0, 60.0, 0.1, 0.2, 0.4, 1.0, 2.365, None, 15.0, name="matrix15")
    return {"3.5MHz": VOLUME_PROBES["swept3"], "7MHz": VOLUME_PROBES["matrix7"], "15MHz": p15}


@dataclass
class Case:
    name: str
    kind: str                 # "affine" or "sphere"
    level: float              # mean axial compression (fraction)
    snr_db: float
    shear: dict = field(default_factory=dict)
    rotation_deg: tuple = (0.0, 0.0, 0.0)
    element_size: float | None = None


FIELDS = (
    Case("comp0.5", "affine", 0.005, 30.0),
    Case("comp2", "affine", 0.02, 20.0),
    Case("comp5", "affine", 0.05, 20.0),
    Case("shear1", "affine", 0.01, 20.0, shear={"xy": 0.01}, rotation_deg=(0.0, 0.0, 0.5)),
    Case("comp1_snr10", "affine", 0.01, 10.0),
    Case("comp1_h1_snr10", "affine", 0.01, 10.0, element_size=1.0),
    Case("sphere1", "sphere", 0.01, 20.0),
    Case("sphere1_snr10", "sphere", 0.01, 10.0),
    Case("sphere2_h1", "sphere", 0.02, 20.0, element_size=1.0),
)


class SphereField:
    """The paper's HI 3D FE solution at ``scale`` x 1 mm patch compression, minus its displacement at ``centre``
    (a translation: the strain is the FE one); ``inside`` the sphere (doubled echo amplitude)."""

    def __init__(self, unit, scale, centre):
        self.unit, self.scale = unit, float(scale)
        self.u0 = unit.displacement(np.asarray(centre, float)[None])[0]
        self.name = f"stiff sphere x{scale:.3f}"

    def displacement(self, points):
        return self.scale * (self.unit.displacement(points) - self.u0)

    def strain(self, points):
        return self.scale * self.unit.strain(points)

    def inside(self, points):
        return self.unit.inside(points)


def make_field(case: Case):
    from forward.volume import Affine3D, FEVolumeField, ImagingVolume

    centre = (TOP_MM + SIZE_MM[0] / 2, 0.0, 0.0)
    if case.kind == "affine":
        return Affine3D(case.level, shear=case.shear, rotation_deg=case.rotation_deg, centre=centre)
    from forward.elasticity import cached_solve
    from forward.sequences import BACKGROUND_MODULUS, INCLUSIONS

    sol = cached_solve("3d", inclusion_modulus=INCLUSIONS["HI"], background_modulus=BACKGROUND_MODULUS,
                       inclusion_depth_mm=30.0, inclusion_diameter_mm=15.0, compression_mm=1.0)
    unit = FEVolumeField(sol, 1.0, name="3d-HI")
    g = ImagingVolume.centred(SIZE_MM, (0.25, 0.25, 0.25), top_mm=TOP_MM)
    mean_exx = float(np.nanmean(unit.strain(g.points()[::7])[:, 0]))
    return SphereField(unit, case.level / -mean_exx, centre)


def run_case(case: Case, probe_name: str, probe, seed: int, regularizer: str = "momentum-stress") -> dict:
    import femreg
    import volume_study as VS
    from femreg.autoalpha import choose_alpha
    from femreg.volume import register_volume, voxel_image_term
    from forward.volume import make_volume_pair

    pair = make_volume_pair(make_field(case), probe, SIZE_MM, top_mm=TOP_MM, snr_db=case.snr_db, seed=seed)
    ref, mov = pair.ref.astype(float), pair.mov.astype(float)
    sl = (slice(None),) * 3
    kw = dict(spacing=pair.spacing, origin=pair.origin, regularizer=regularizer)
    if case.element_size is not None:
        kw["element_size"] = case.element_size

    def err(res):
        return VS.volume_errors_3d(res, pair, 1, sl, pair.origin)["e6"] / 100.0

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = time.process_time()
        ch = choose_alpha(ref, mov, keep_results=True, register=register_volume, image_term=voxel_image_term, **kw)
        cpu_auto = time.process_time() - c0
        c0 = time.process_time()
        plain = femreg.register(ref, mov, **kw)
        cpu_default = time.process_time() - c0
    e = np.array([err(r) for r in ch.results])
    ok = [bool(r.success) for r in ch.results]
    k = int(np.argmin(np.abs(np.log(ch.alphas / ch.alpha))))
    good = np.where(ok, e, np.inf)
    best = int(np.argmin(good)) if np.isfinite(good).any() else int(np.argmin(e))
    e_def = err(plain)
    return dict(case=case.name, probe=probe_name, regularizer=regularizer, seed=seed, shape=list(ref.shape),
                snr_db=case.snr_db, element_size=case.element_size or 2.0, auto_alpha=float(ch.alpha),
                best_alpha=float(ch.alphas[best]), default_alpha=float(plain.alpha), e_auto=float(e[k]),
                e_best=float(e[best]), e_default=float(e_def), e_grid_centre=float(e[len(e) // 2]),
                ratio=float(e[k] / e[best]), ratio_default=float(e_def / e[best]), success=ok,
                default_success=bool(plain.success), curve=[float(x) for x in e],
                alphas=[float(a) for a in ch.alphas], strain_change=[float(x) for x in ch.strain_change],
                cpu_auto=cpu_auto, cpu_default=cpu_default)


def _within(e, best):
    r, d = e / best, 100.0 * (e - best)
    return r <= WITHIN, d <= POINTS, (r <= WITHIN) | (d <= POINTS)


def summary(rows) -> str:
    L = ["| probe | cases | auto: within 15 % / 0.5 pt / either | median / max ratio | default: within 15 % / "
         "0.5 pt / either | median / max ratio | auto better / worse than default | auto - default: median, "
         "range (points) | CPU auto / default |",
         "|---|---|---|---|---|---|---|---|---|"]
    groups = [(p, [r for r in rows if r["probe"] == p]) for p in dict.fromkeys(r["probe"] for r in rows)]
    for lab, rs in groups + [("all", rows)]:
        best = np.array([r["e_best"] for r in rs])
        ea, ed = np.array([r["e_auto"] for r in rs]), np.array([r["e_default"] for r in rs])
        wa, wd = _within(ea, best), _within(ed, best)
        n = len(rs)
        cpu = np.median([r["cpu_auto"] / r["cpu_default"] for r in rs])
        L.append(f"| {lab} | {n} | {wa[0].sum()} / {wa[1].sum()} / {wa[2].sum()} | {np.median(ea / best):.2f} / "
                 f"{np.max(ea / best):.2f} | {wd[0].sum()} / {wd[1].sum()} / {wd[2].sum()} | "
                 f"{np.median(ed / best):.2f} / {np.max(ed / best):.2f} | {int(np.sum(ea < ed))} / "
                 f"{int(np.sum(ea > ed))} | {100 * np.median(ea - ed):+.2f}, {100 * np.min(ea - ed):+.2f} .. "
                 f"{100 * np.max(ea - ed):+.2f} | {np.median([r['cpu_auto'] for r in rs]):.1f} s / "
                 f"{np.median([r['cpu_default'] for r in rs]):.1f} s (x{cpu:.1f}) |")
    L += ["", "| case | probe | auto alpha | e at auto | best alpha | e at best | ratio | default: e | "
          "CPU auto / default |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['case']} | {r['probe']} | {r['auto_alpha']:.3g} | {100 * r['e_auto']:.2f} % | "
                 f"{r['best_alpha']:.3g} | {100 * r['e_best']:.2f} % | {r['ratio']:.2f} | "
                 f"{100 * r['e_default']:.2f} % | {r['cpu_auto']:.1f} / {r['cpu_default']:.1f} s |")
    return "\n".join(L) + "\n"


def _cell(key, text):
    """A value of the .csv back as the row held it."""
    if key in ("curve", "alphas", "strain_change", "success", "shape"):
        return json.loads(text)
    if key in ("case", "probe", "regularizer"):
        return text
    return text == "True" if text in ("True", "False") else float(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=tuple(SEED_BASE), default="A", help="seed set (B: held out)")
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--probes", default="", help="comma-separated probe labels (3.5MHz, 7MHz, 15MHz)")
    ap.add_argument("--regularizer", default="momentum-stress", help="the regulariser (default: femreg's)")
    ap.add_argument("--out", default="out/autoalpha_volume")
    ap.add_argument("--summarise", action="store_true", help="only rewrite the .md from the .csv")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = a.set if a.regularizer == "momentum-stress" else f"{a.set}_{a.regularizer}"
    path = out / f"{stem}.csv"
    if a.summarise:
        with open(path) as fh:
            rows = [{k: _cell(k, v) for k, v in r.items()} for r in csv.DictReader(fh)]
    else:
        P = probes()
        words = [w for w in a.cases.split(",") if w]
        pw = [w for w in a.probes.split(",") if w]
        jobs = [(c, pn) for pn in P for c in FIELDS if (not words or any(w in c.name for w in words))
                and (not pw or pn in pw)]
        rows = []
        with open(path, "w", newline="") as fh:     # row by row: an interrupted run keeps its rows
            w = None
            for i, (c, pn) in enumerate(jobs):
                seed = SEED_BASE[a.set] + 10 * list(P).index(pn) + FIELDS.index(c)
                r = run_case(c, pn, P[pn], seed, a.regularizer)
                rows.append(r)
                print(f"{c.name} {pn}: auto {r['auto_alpha']:.3g} e {100 * r['e_auto']:.2f} %, best "
                      f"{r['best_alpha']:.3g} {100 * r['e_best']:.2f} %, default {100 * r['e_default']:.2f} %, "
                      f"CPU {r['cpu_auto']:.1f} / {r['cpu_default']:.1f} s", file=sys.stderr, flush=True)
                w = write_row(fh, w, r)
    md = summary(rows) + f"\nseed set {a.set}, {a.regularizer}, {len(rows)} cases\n"
    (out / f"{stem}.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
