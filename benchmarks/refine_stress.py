"""Stress test of the default adaptive refinement (:data:`femreg.refine.DEEP_REFINEMENT`) on simulated pairs unlike
those its rules were tuned on (the robustness, inclusion-size and plane-strain-model benchmarks).

Each pair is registered twice with R_P_sigma, ``femreg.register(ref, mov, spacing=..., origin=...)`` (the default
``refine``) and with ``refine=None``.  Measured per pair: the total strain error ``e`` (%, relative L2 of ``e_xx,
e_yy, e_xy`` over the robustness ROI, :func:`benchmarks.robustness.errors`), CPU seconds of each registration
(``time.process_time``, the least of ``--repeats`` runs, default 3: a registration takes 0.05-1 s here, one run's
CPU time varies by up to 2x), the elements of each final mesh, ``res.success`` / ``res.message`` and the
refinement's note.  A pair is flagged where the default is

* ``worse``: more than 0.3 points above ``refine=None``;
* ``fail``: ``success`` False where ``refine=None`` succeeds;
* ``nan``: a non-finite error;
* ``raise``: an exception (the other column then reads ``error``);
* ``slow``: more than 3x the CPU time of ``refine=None``.

Pairs (:data:`CASES`, a fixed seed each; :func:`forward.pairs.make_pair`, exact truth):

* probes outside :data:`forward.pairs.PROBES`: ``HF13`` (13 MHz, 0.075 mm pitch, 0.45 mm beam), ``HF12w``
  (12 MHz, 0.1 mm pitch, a 1 mm beam: 10 lines per beam), ``C3`` (3 MHz, 0.5 mm pitch, 3 mm beam, 16 MHz
  sampling);
* 0.1 % and 10 % compression with stiff / soft inclusions (plane strain and plane stress, r 2-6 mm);
* gain change of the moving frame (x1.5; a depth ramp of 0 -> +6 dB or 0 -> -8 dB over the image);
* out-of-plane decorrelation: the moving frame ``sqrt(1 - rho^2) mov + rho mov'``, ``mov'`` an independent speckle
  realisation moved by the same field (rho 0.2, 0.3 and 0.55, i.e. 4 %, 9 % and 30 % of the energy new);
* SNR 10 dB; 10 x 10 mm and 60 x 40 mm images;
* an in-plane rotation about the probe-face centre composed with an inclusion (``u(X) = R (X + u_inc(X)) - X``,
  strain by central differences of that ``u``): 5 degrees under the paper's probe, 7.5 MHz and 15 MHz, 3-4 degrees
  under 12 MHz (``benchmarks/rotation_sweep.py`` stops at 4 degrees: beyond, the speckle decorrelates and the
  registration should say it failed).

Outputs (``--out``, default ``out/refine_stress/``): ``results.md`` (the table printed) and ``results.csv``.

Run: ``python benchmarks/refine_stress.py [--cases words] [--out dir] [--repeats 3] [--seed 0] [--list]``
(``--cases``: comma-separated words, cases whose name contains one; about 4 min for all 33 pairs on one core).
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import errors, roi_slices, truth  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import Probe, as_probe, make_pair  # noqa: E402

#: Probes not among the presets the refinement rules were tuned on.
STRESS_PROBES = {
    "HF13": Probe(13.0, 60.0, 0.075, 0.45, name="HF13"),
    "HF12w": Probe(12.0, 50.0, 0.1, 1.0, name="HF12w"),
    "C3": Probe(3.0, 16.0, 0.5, 3.0, cycles=2.0, name="C3"),
}

#: Points above ``refine=None`` (total strain error, %) from which the default counts as worse.
WORSE_POINTS = 0.3
#: CPU time ratio default / ``refine=None`` above which the default counts as slow.
SLOW_RATIO = 3.0


class Rotated:
    """``field`` followed by a rigid rotation by ``deg`` about the probe-face centre: ``u(X) = R (X + u_f(X)) - X``.
    Strain: small strain of that ``u`` by central differences (step ``h`` mm); ``inside`` as ``field``'s."""

    def __init__(self, field, deg: float, h: float = 1e-3):
        self.field, self.h = field, float(h)
        th = math.radians(float(deg))
        self.R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        self.level = getattr(field, "level", 0.0)
        self.name = f"{getattr(field, 'name', 'field')} + rotation {deg:g} deg"
        if callable(getattr(field, "inside", None)):
            self.inside = field.inside

    def displacement(self, points) -> np.ndarray:
        p = F.as_points(points)
        return (p + self.field.displacement(p)) @ self.R.T - p

    def strain(self, points) -> np.ndarray:
        p, h = F.as_points(points), self.h
        gx = (self.displacement(p + [h, 0]) - self.displacement(p - [h, 0])) / (2 * h)
        gy = (self.displacement(p + [0, h]) - self.displacement(p - [0, h])) / (2 * h)
        return np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])


@dataclass
class StressCase:
    """One pair: the field (built lazily), the probe, the image (depth, width) mm from ``top_mm``, SNR dB, seed, and
    what is done to the moving frame after rendering (``gain``, ``ramp_db``, ``rho``)."""

    name: str
    field: object            # callable () -> field
    probe: str               # a key of STRESS_PROBES or PROBES
    size_mm: tuple
    snr_db: float
    top_mm: float = 2.0
    seed: int = 0
    gain: float | None = None        # moving frame times this
    ramp_db: float | None = None     # moving frame times a gain of 0 -> ramp_db dB from top to bottom
    rho: float | None = None         # moving frame mixed with an independent realisation, amplitude weight rho
    notes: str = ""


def _inc(kind, model, level, r, rot=None):
    def build():
        f = F.Inclusion(kind, model, level, radius_mm=r)
        return f if rot is None else Rotated(f, rot)
    return build


def _comp(level):
    return lambda: F.compression(level)


CASES = [
    # fine-pitch high-frequency probes (the inclusion 20 mm deep: the image around it)
    StressCase("hf13_stiff-pstrain1_r3", _inc("stiff", "plane-strain", 0.01, 3), "HF13", (15, 15), 30, 12.5, 101),
    StressCase("hf13_soft-pstress2_r2", _inc("soft", "plane-stress", 0.02, 2), "HF13", (12, 12), 25, 14.0, 102),
    StressCase("hf13_comp0.5", _comp(0.005), "HF13", (15, 15), 30, 5.0, 103),
    StressCase("hf12w_stiff-pstress1_r4", _inc("stiff", "plane-stress", 0.01, 4), "HF12w", (20, 20), 25, 10.0, 104),
    StressCase("hf12w_soft-pstrain4_r3", _inc("soft", "plane-strain", 0.04, 3), "HF12w", (20, 20), 30, 10.0, 105),
    # coarse 3 MHz probe
    StressCase("c3_stiff-pstrain1_r6", _inc("stiff", "plane-strain", 0.01, 6), "C3", (50, 40), 20, 2.0, 106),
    StressCase("c3_soft-pstress3_r5", _inc("soft", "plane-stress", 0.03, 5), "C3", (40, 40), 20, 2.0, 107),
    StressCase("c3_comp2", _comp(0.02), "C3", (50, 40), 25, 2.0, 108),
    # 0.1 % and 10 % strain
    StressCase("s0.1_stiff-pstrain_r4_paper", _inc("stiff", "plane-strain", 0.001, 4), "paper", (35, 30), 30, 2.0, 109),
    StressCase("s0.1_soft-pstress_r3_L7", _inc("soft", "plane-stress", 0.001, 3), "L7", (30, 30), 30, 5.0, 110),
    StressCase("s0.1_stiff-pstress_r2_L12", _inc("stiff", "plane-stress", 0.001, 2), "L12", (15, 15), 30, 12.5, 111),
    StressCase("s10_stiff-pstrain_r5_paper", _inc("stiff", "plane-strain", 0.10, 5), "paper", (35, 30), 30, 2.0, 112),
    StressCase("s10_soft-pstress_r4_L7", _inc("soft", "plane-stress", 0.10, 4), "L7", (30, 30), 30, 5.0, 113),
    StressCase("s10_soft-pstrain_r6_L3", _inc("soft", "plane-strain", 0.10, 6), "L3", (40, 40), 25, 2.0, 114),
    # gain change between the frames
    StressCase("gain1.5_stiff-pstrain2_r4_paper", _inc("stiff", "plane-strain", 0.02, 4), "paper", (35, 30), 25,
               2.0, 115, gain=1.5),
    StressCase("ramp+6_soft-pstrain2_r3_L7", _inc("soft", "plane-strain", 0.02, 3), "L7", (30, 30), 25, 5.0, 116,
               ramp_db=6.0),
    StressCase("ramp-8_comp1_paper", _comp(0.01), "paper", (40, 30), 25, 2.0, 117, ramp_db=-8.0),
    # out-of-plane decorrelation
    StressCase("decor0.2_stiff-pstrain1_r4_paper", _inc("stiff", "plane-strain", 0.01, 4), "paper", (35, 30), 25,
               2.0, 118, rho=0.2),
    StressCase("decor0.3_soft-pstress2_r3_L7", _inc("soft", "plane-stress", 0.02, 3), "L7", (30, 30), 25, 5.0, 119,
               rho=0.3),
    StressCase("decor0.3_comp1_L12", _comp(0.01), "L12", (25, 25), 25, 5.0, 120, rho=0.3),
    StressCase("decor0.55_stiff-pstress2_r5_paper", _inc("stiff", "plane-stress", 0.02, 5), "paper", (35, 30), 25,
               2.0, 121, rho=0.55),
    # low SNR
    StressCase("snr10_stiff-pstrain1_r4_paper", _inc("stiff", "plane-strain", 0.01, 4), "paper", (35, 30), 10,
               2.0, 122),
    StressCase("snr10_soft-pstrain3_r3_L12", _inc("soft", "plane-strain", 0.03, 3), "L12", (25, 25), 10, 7.5, 123),
    StressCase("snr10_comp0.5_L7", _comp(0.005), "L7", (30, 30), 10, 2.0, 124),
    # image size
    StressCase("small10_stiff-pstrain1_r2_L7", _inc("stiff", "plane-strain", 0.01, 2), "L7", (10, 10), 30, 15.0, 125),
    StressCase("small10_soft-pstress3_r2_paper", _inc("soft", "plane-stress", 0.03, 2), "paper", (10, 10), 25, 15.0,
               126),
    StressCase("large60x40_stiff-pstrain1_r6_paper", _inc("stiff", "plane-strain", 0.01, 6), "paper", (60, 40), 25,
               2.0, 127),
    StressCase("large60x40_soft-pstress2_r5_L7", _inc("soft", "plane-stress", 0.02, 5), "L7", (60, 40), 25, 2.0, 128),
    # rotation plus an inclusion
    StressCase("rot5_stiff-pstrain1_r4_paper", _inc("stiff", "plane-strain", 0.01, 4, rot=5.0), "paper", (35, 30), 25,
               2.0, 129),
    StressCase("rot5_soft-pstress2_r3_L7", _inc("soft", "plane-stress", 0.02, 3, rot=5.0), "L7", (30, 30), 25, 5.0,
               130),
    StressCase("rot5_stiff-pstrain1_r3_L15", _inc("stiff", "plane-strain", 0.01, 3, rot=5.0), "L15", (15, 15), 25,
               12.5, 133),
    StressCase("rot4_soft-pstress2_r3_L12", _inc("soft", "plane-stress", 0.02, 3, rot=4.0), "L12", (30, 30), 25, 5.0,
               132),
    StressCase("rot3_stiff-pstrain1_r4_L12", _inc("stiff", "plane-strain", 0.01, 4, rot=3.0), "L12", (30, 30), 25,
               5.0, 131),
]


def probe_of(name: str) -> Probe:
    return STRESS_PROBES[name] if name in STRESS_PROBES else as_probe(name)


def make_stress_pair(case: StressCase):
    """(pair, moving frame): the :class:`forward.pairs.Pair` of ``case`` and its moving frame after the case's
    gain / ramp / decorrelation (the truth is the pair's field in every case)."""
    field = case.field()
    pr = probe_of(case.probe)
    data = make_pair(field, pr, case.size_mm, case.snr_db, case.seed, top_mm=case.top_mm, name=case.name)
    mov = np.array(data.mov, float)
    if case.rho is not None:
        other = make_pair(field, pr, case.size_mm, None, case.seed + 1000, top_mm=case.top_mm).mov
        mov = math.sqrt(1.0 - case.rho ** 2) * mov + case.rho * other * (np.std(mov) / np.std(other))
    if case.ramp_db is not None:
        mov = mov * 10.0 ** (np.linspace(0.0, case.ramp_db, mov.shape[0]) / 20.0)[:, None]
    if case.gain is not None:
        mov = mov * case.gain
    return data, mov


def _register(ref, mov, data, kw, repeats=1):
    """(result, least CPU seconds over ``repeats`` runs) of ``femreg.register`` with the keywords ``kw``."""
    import femreg

    best = np.inf
    for _ in range(max(1, int(repeats))):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c0 = time.process_time()
            res = femreg.register(ref, mov, spacing=data.spacing, origin=data.origin, **kw)
            best = min(best, time.process_time() - c0)
    return res, best


def measure(case: StressCase, repeats: int = 1) -> dict:
    """Errors, CPU seconds, elements, success and message of ``refine=None`` ("off") and the default ("on")."""
    t0 = time.perf_counter()
    data, mov = make_stress_pair(case)
    t_sim = time.perf_counter() - t0
    sl = roi_slices(data.ref.shape, data.spacing)
    t = truth(data, None, sl)
    lam = probe_of(case.probe).wavelength_mm
    row = dict(case=case.name, shape="x".join(map(str, data.ref.shape)), sim_s=t_sim)
    for key, kw in (("off", dict(refine=None)), ("on", {})):
        try:
            res, cpu = _register(data.ref, mov, data, kw, repeats)
            rec = getattr(res, "refinement", None)
            row.update({f"e_{key}": 100 * errors(res.on_grid(), t, sl, lam)["e"], f"cpu_{key}": cpu,
                        f"el_{key}": int(res.mesh.t.shape[1]), f"ok_{key}": bool(res.success),
                        f"msg_{key}": str(res.message),
                        f"note_{key}": str(getattr(rec, "note", "") or "") if rec is not None else ""})
        except Exception as exc:  # noqa: BLE001 -- a raise is a result of the benchmark
            row.update({f"e_{key}": float("nan"), f"cpu_{key}": float("nan"), f"el_{key}": 0, f"ok_{key}": False,
                        f"msg_{key}": f"error: {type(exc).__name__}: {exc}"[:200], f"note_{key}": "",
                        f"raised_{key}": True})
    row["flags"] = flags(row)
    return row


def flags(row) -> str:
    f = []
    if row.get("raised_on"):
        f.append("raise")
    elif not math.isfinite(row["e_on"]):
        f.append("nan")
    if math.isfinite(row["e_on"]) and math.isfinite(row["e_off"]) and row["e_on"] - row["e_off"] > WORSE_POINTS:
        f.append("worse")
    if row["ok_off"] and not row["ok_on"] and not row.get("raised_on"):
        f.append("fail")
    if row["cpu_off"] > 0 and row["cpu_on"] / row["cpu_off"] > SLOW_RATIO:
        f.append("slow")
    return " ".join(f)


def table(rows) -> str:
    out = ["| case | pixels | e % None -> default | points | CPU s None / default | ratio | elements | success | "
           "flags |\n", "|---|---|---|---|---|---|---|---|---|\n"]
    for r in rows:
        ok = "" if r["ok_off"] and r["ok_on"] else f"{r['ok_off']} -> {r['ok_on']}"
        out.append(f"| {r['case']} | {r['shape']} | {r['e_off']:.2f} -> {r['e_on']:.2f} | "
                   f"{r['e_on'] - r['e_off']:+.2f} | {r['cpu_off']:.2f} / {r['cpu_on']:.2f} | "
                   f"{r['cpu_on'] / r['cpu_off']:.2f} | {r['el_off']} -> {r['el_on']} | {ok or 'yes'} | "
                   f"{r['flags'] or '-'} |\n")
    notes = [f"- {r['case']}: default: {r['msg_on']}" + (f"; refinement: {r['note_on']}" if r["note_on"] else "")
             + ("" if r["ok_off"] else f"; refine=None: {r['msg_off']}")
             for r in rows if r["flags"] or not r["ok_off"] or not r["ok_on"] or r["note_on"]]
    d = [r["e_on"] - r["e_off"] for r in rows if math.isfinite(r["e_on"] - r["e_off"])]
    q = [r["cpu_on"] / r["cpu_off"] for r in rows if r["cpu_off"] > 0 and math.isfinite(r["cpu_on"])]
    summary = (f"\n{len(rows)} pairs, {sum(bool(r['flags']) for r in rows)} flagged; largest error increase "
               f"{max(d, default=float('nan')):+.2f} points, largest decrease {min(d, default=float('nan')):+.2f}; "
               f"CPU ratio median {np.median(q) if q else float('nan'):.2f}, max {max(q, default=float('nan')):.2f}\n")
    return "".join(out) + summary + ("\nMessages / notes:\n\n" + "\n".join(notes) + "\n" if notes else "")


def warm_up():
    """One small registration of each kind, not timed: compiled kernels ready before the first case."""
    d = make_pair(F.compression(0.01), "L7", (12.0, 10.0), 30.0, 0)
    _register(d.ref, d.mov, d, dict(refine=None))
    _register(d.ref, d.mov, d, {})


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--out", default="out/refine_stress", help="output folder (default out/refine_stress)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--repeats", type=int, default=3, help="runs per registration; CPU time: the least (default 3)")
    ap.add_argument("--seed", type=int, default=0,
                    help="added to every case's seed: other speckle and noise realisations of the same pairs")
    a = ap.parse_args(argv)
    from benchmarks.refine_cost import selected_cases

    cases = selected_cases(CASES, a.cases, a.seed)
    if a.list:
        for c in CASES:
            print(f"{c.name:36s} probe {c.probe:6s} {c.size_mm[0]}x{c.size_mm[1]} mm SNR {c.snr_db} dB seed {c.seed}")
        return 0
    if not cases:
        print("no case selected (see --list)", file=sys.stderr)
        return 2
    warm_up()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    keys = ["case", "shape", "sim_s", "e_off", "e_on", "cpu_off", "cpu_on", "el_off", "el_on", "ok_off", "ok_on",
            "flags", "msg_off", "msg_on", "note_off", "note_on"]
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for c in cases:
            r = measure(c, a.repeats)
            rows.append(r)
            w.writerow(r)
            fh.flush()
            print(f"# {c.name}: sim {r['sim_s']:.1f} s, e {r['e_off']:.2f} -> {r['e_on']:.2f} %, CPU "
                  f"{r['cpu_off']:.2f} / {r['cpu_on']:.2f} s, {r['flags'] or 'ok'}", file=sys.stderr, flush=True)
    md = "## Default refinement against refine=None (R_P_sigma), stress pairs\n\n" + table(rows)
    (out / "results.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
