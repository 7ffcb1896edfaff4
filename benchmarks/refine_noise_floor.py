"""The default refinement on pairs whose echo fades into the receiver's noise floor with depth (no time-gain
compensation), the noise-explained part of the element NCC taken out of its decorrelation test or not.

The test "the speckle decorrelates in parts of the image" (:data:`femreg.refine.DECORRELATED_SPREAD`, the spread of
the unrefined solve's element NCC) reads an echo that sinks towards the noise with depth as decorrelation: the deep
elements' NCC falls as the noise's share of their power grows (NCC ``S / (S + N)``), and refinement was switched
off on such recordings.  :func:`femreg.refine.noise_ncc` computes the NCC that noise alone leaves per element from
the noise floor :func:`femreg.register`'s echo detection measured (:func:`femreg.echo.noise_share`), and
:func:`femreg.refine.decorrelation_ncc` takes it out before the spread is read.

Pairs (:func:`forward.pairs.make_pair` with :func:`forward.pairs.attenuation_gain_db` set by
:func:`forward.pairs.alpha_for_floor`: the echo meets the noise at ``floor`` mm; the probes of
``benchmarks/refine_stress.py`` too), among them pairs with out-of-plane decorrelation on top (the moving frame
mixed with an independent realisation, as there), where refinement should still hold back.  Three registrations
each: ``refine=None``; the default refinement without the noise's part (``before``); the default (``after``).
Total strain error (%, :func:`benchmarks.robustness.errors`) over the robustness ROI within the registered echo
rectangle (the rows left out for the noise are NaN in every result and not scored), the elements of each mesh,
and the refinement's note.

Run: ``python benchmarks/refine_noise_floor.py [--cases words]`` (about 2 min on one core).
"""
from __future__ import annotations

import argparse
import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.refine_stress import STRESS_PROBES, _comp, _inc  # noqa: E402
from benchmarks.robustness import errors, roi_slices, truth  # noqa: E402
from forward.pairs import alpha_for_floor, as_probe, attenuation_gain_db, make_pair  # noqa: E402


@dataclass
class FloorCase:
    name: str
    field: object           # callable () -> field
    probe: str
    size_mm: tuple
    snr_db: float           # at the probe face
    floor_mm: float         # depth where the echo meets the noise
    top_mm: float = 2.0
    seed: int = 0
    rho: float | None = None


CASES = [
    FloorCase("stiff-pstrain1_r4_paper", _inc("stiff", "plane-strain", 0.01, 4), "paper", (40, 30), 30, 34, 2, 201),
    FloorCase("soft-pstress2_r3_L7", _inc("soft", "plane-stress", 0.02, 3), "L7", (30, 30), 30, 30, 5, 202),
    FloorCase("stiff-pstress1_r4_L3", _inc("stiff", "plane-stress", 0.01, 4), "L3", (45, 40), 30, 38, 2, 203),
    FloorCase("stiff-pstrain1_r3_L12", _inc("stiff", "plane-strain", 0.01, 3), "L12", (25, 25), 30, 28, 7.5, 204),
    FloorCase("soft-pstrain4_r2_HF13", _inc("soft", "plane-strain", 0.04, 2), "HF13", (15, 15), 30, 25, 12.5, 205),
    FloorCase("soft-pstress3_r5_C3", _inc("soft", "plane-stress", 0.03, 5), "C3", (45, 40), 25, 40, 2, 206),
    FloorCase("comp1_paper", _comp(0.01), "paper", (40, 30), 30, 32, 2, 207),
    FloorCase("comp0.3_L7", _comp(0.003), "L7", (30, 30), 25, 26, 5, 208),
    FloorCase("rot3_stiff-pstrain1_r4_L12", _inc("stiff", "plane-strain", 0.01, 4, rot=3.0), "L12", (30, 30), 30,
              30, 5, 209),
    FloorCase("decor0.2_stiff-pstrain1_r4_paper", _inc("stiff", "plane-strain", 0.01, 4), "paper", (40, 30), 30, 34,
              2, 210, rho=0.2),
    FloorCase("decor0.3_soft-pstress2_r3_L7", _inc("soft", "plane-stress", 0.02, 3), "L7", (30, 30), 30, 30, 5, 211,
              rho=0.3),
    FloorCase("decor0.3_comp1_L12", _comp(0.01), "L12", (25, 25), 30, 28, 7.5, 212, rho=0.3),
]


def make_floor_pair(case: FloorCase):
    """(pair, moving frame) of ``case``: the echo attenuated without TGC into the noise at ``floor_mm``; with
    ``rho`` the moving frame mixed with an independent realisation (out-of-plane decorrelation)."""
    pr = STRESS_PROBES.get(case.probe) or as_probe(case.probe)
    gain = attenuation_gain_db(alpha_for_floor(case.floor_mm, case.snr_db, pr.f0_mhz), pr.f0_mhz)
    field = case.field()
    data = make_pair(field, pr, case.size_mm, case.snr_db, case.seed, top_mm=case.top_mm, echo_gain_db=gain)
    mov = np.array(data.mov, float)
    if case.rho is not None:
        other = make_pair(field, pr, case.size_mm, case.snr_db, case.seed + 1000, top_mm=case.top_mm,
                          echo_gain_db=gain).mov
        mov = math.sqrt(1.0 - case.rho ** 2) * mov + case.rho * other * (np.std(mov) / np.std(other))
    return data, mov, pr


def _scored(res, t, sl, lam):
    """Total strain error (%) over the ROI samples where the result is finite (the echo rectangle)."""
    g = res.on_grid()
    ok = np.isfinite(np.asarray(g["exx"], float)[sl])
    rows = np.flatnonzero(ok.any(axis=1))
    if not rows.size:
        return float("nan")
    r1 = rows[-1] + 1
    sub = (slice(sl[0].start, sl[0].start + r1 * sl[0].step, sl[0].step), sl[1])
    tt = {k: v[:r1] for k, v in t.items()}
    return 100 * errors(g, tt, sub, lam)["e"]


def measure(case: FloorCase) -> dict:
    import femreg

    data, mov, pr = make_floor_pair(case)
    sl = roi_slices(data.ref.shape, data.spacing)
    t = truth(data, None, sl)
    row = dict(case=case.name)
    runs = (("off", dict(refine=None), False), ("before", {}, True), ("after", {}, False))
    for key, kw, blind in runs:
        with warnings.catch_warnings(), (mock.patch("femreg.echo.crop_noise_share", lambda: None) if blind
                                          else _null()):
            warnings.simplefilter("ignore")
            res = femreg.register(data.ref, mov, spacing=data.spacing, origin=data.origin, **kw)
        rec = getattr(res, "refinement", None)
        row[f"e_{key}"] = _scored(res, t, sl, pr.wavelength_mm)
        row[f"el_{key}"] = int(res.mesh.t.shape[1])
        row[f"ok_{key}"] = bool(res.success)
        row[f"note_{key}"] = (str(getattr(rec, "note", "") or "") if rec is not None else "")[:90]
        row["excluded"] = str(getattr(res, "excluded", "") or "")[:60]
    return row


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="", help="comma-separated words: cases whose name contains one")
    a = ap.parse_args(argv)
    words = [w for w in a.cases.split(",") if w]
    print("| case | e % None | before | after | after - before | elements None / before / after | note before | "
          "note after |")
    print("|---|---|---|---|---|---|---|---|")
    for case in CASES:
        if words and not any(w in case.name for w in words):
            continue
        r = measure(case)
        print(f"| {r['case']} | {r['e_off']:.2f} | {r['e_before']:.2f} | {r['e_after']:.2f} | "
              f"{r['e_after'] - r['e_before']:+.2f} | {r['el_off']} / {r['el_before']} / {r['el_after']} | "
              f"{r['note_before'] or '-'} | {r['note_after'] or '-'} |", flush=True)


if __name__ == "__main__":
    main()
