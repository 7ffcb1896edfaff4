"""Speed of ``femreg.invert``: one inversion on meshes of ~800 and ~3000 nodes (targets 10 s and 60 s).

Data: the exact plane-stress HI forward solution (forward.solve_elasticity, 1 mm P2) over the paper's imaged area
(x 1-71 mm, y -21-21 mm), inverted with the plane-stress model.  Printed per mesh: nodes, elements, seconds for
one inversion at a given beta (1e-3), L-BFGS-B iterations and forward/adjoint evaluations, and the seconds of the
default beta rule (L-curve sweep, several inversions), with the recovered contrast (truth 4).

Usage: ``python benchmarks/bench_invert.py``.  Timings on a shared 2-core machine are pessimistic.

Measured (2026-11-29, shared 2-core machine, load ~8): 792 nodes 0.5 s for one inversion (96 L-BFGS-B
iterations), 2.1 s with the beta rule; 3053 nodes 3.6 s (169 iterations), 12.6 s with the rule.  Contrast 4.08-4.17
(true 4).
"""
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import forward  # noqa: E402
from femreg import invert  # noqa: E402
from femreg.inversion import modulus_contrast  # noqa: E402

REGION = ((1.0, 71.0), (-21.0, 21.0))
#: element sizes giving ~800 and ~3000 nodes on the region
SIZES = {"~800 nodes": (2.0, 2.0), "~3000 nodes": (1.0, 1.0)}


def main():
    sol = forward.solve_elasticity("plane-stress", inclusion_modulus=40.0, mesh_size_mm=1.0)
    roi = lambda p: (np.asarray(p)[:, 0] - 30) ** 2 + np.asarray(p)[:, 1] ** 2 < 7.5 ** 2  # noqa: E731
    print("| mesh | nodes | elements | one inversion (beta 1e-3) s | iterations | evaluations | contrast "
          "| default beta rule s | beta chosen | contrast |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, h in SIZES.items():
        t = time.perf_counter()
        one = invert(sol.displacement, region=REGION, element_size=h, beta=1e-3)
        t_one = time.perf_counter() - t
        t = time.perf_counter()
        auto = invert(sol.displacement, region=REGION, element_size=h)
        t_auto = time.perf_counter() - t
        print(f"| {name} | {one.mesh.p.shape[1]} | {one.mesh.t.shape[1]} | {t_one:.1f} | {one.nit} | "
              f"{one.timings['n_evaluations']} | {modulus_contrast(one, roi)['contrast']:.3f} | {t_auto:.1f} | "
              f"{auto.beta:.2g} | {modulus_contrast(auto, roi)['contrast']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
