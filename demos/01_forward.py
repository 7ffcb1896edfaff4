r"""Demo 01: forward models, the finite-element ground truth
========================================================

This demo shows how to solve the paper's phantom (160 mm block, 15 mm inclusion 30 mm deep, 4x stiffer (HI),
50 mm compression patch, nu = 0.495) as plane strain, plane stress and 3D linear elasticity, and how to sample the
ground-truth strain on the imaged area (44 mm lateral x 72 mm axial from the top surface).

Strong form, per region with Young's modulus E_r:  -div sigma(u) = 0,  sigma = 2 mu eps(u) + lambda tr eps(u) I;
bottom clamped, patch pushed down by ``compression_mm`` with slip (only u_x prescribed), all else traction-free.
Weak form: find u with  int 2 mu eps(u):eps(v) + lambda div u div v = 0  for all admissible v.
P2 triangles (2D) / P2 tetrahedra on a quarter model (3D), MKL PARDISO direct solver.

Run: ``python demos/01_forward.py [--quick]``; output in ``out/01_forward/``.
"""
import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import forward  # noqa: E402

OUT = Path("out/01_forward")

# Mesh sizes (element size in the imaged region, far-field size), mm.  --quick: coarse, seconds.
MESHES = {"plane-strain": (0.5, 8.0), "plane-stress": (0.5, 8.0), "3d": (1.0, 16.0)}
QUICK = {"plane-strain": (2.0, 16.0), "plane-stress": (2.0, 16.0), "3d": (4.0, 16.0)}


def imaged_grid(step=0.2):
    """Pixel grid of the imaged area: x (axial) 0..72 mm, y (lateral) -22..22 mm."""
    x = np.arange(0.0, 72.0 + 1e-9, step)
    y = np.arange(-22.0, 22.0 + 1e-9, step)
    return x, y, np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1).reshape(-1, 2)


def visualize(results, path):
    """One row per model, columns e_xx (axial), e_yy (lateral), e_xy (shear); strains in %."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["axial $\\varepsilon_{xx}$", "lateral $\\varepsilon_{yy}$", "shear $\\varepsilon_{xy}$"]
    fig, axes = plt.subplots(len(results), 3, figsize=(10, 4.3 * len(results)), squeeze=False)
    for r, (model, (x, y, e)) in enumerate(results.items()):
        for c in range(3):
            ax = axes[r, c]
            im = ax.imshow(100 * e[:, :, c], extent=(y[0], y[-1], x[-1], x[0]), cmap="jet", aspect="equal")
            ax.set_title(f"{model}: {names[c]} [%]")
            ax.set_xlabel("lateral y [mm]")
            ax.set_ylabel("axial x [mm]")
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description="Solve the three HI forward models and plot their strains.")
    ap.add_argument("--quick", action="store_true", help="coarse meshes (seconds)")
    a = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    meshes = QUICK if a.quick else MESHES
    x, y, pts = imaged_grid(0.5 if a.quick else 0.2)
    results = {}
    print(f"{'model':>13} {'DOFs':>8} {'mesh s':>7} {'assembly s':>10} {'solve s':>8} {'total s':>8} "
          f"{'peak MB':>8} {'eval s':>7} {'SR':>6}")
    for model, (h, hc) in meshes.items():
        sol = forward.solve_elasticity(model, inclusion_modulus=40.0, mesh_size_mm=h, coarse_size_mm=hc)
        t = time.perf_counter()
        e = sol.strain(pts).reshape(len(x), len(y), 3)
        t_eval = time.perf_counter() - t
        lab = sol.region(pts).reshape(len(x), len(y))
        # strain ratio (background / inclusion) of the axial strain over the imaged area, as the paper's SR
        sr = e[:, :, 0][lab == 0].mean() / e[:, :, 0][lab == 1].mean()
        i = sol.info
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"{model:>13} {i['n_dofs']:8d} {i['mesh_time_s']:7.1f} {i['assembly_time_s']:10.1f} "
              f"{i['solve_time_s']:8.1f} {i['total_time_s']:8.1f} {peak:8.0f} {t_eval:7.2f} {sr:6.2f}", flush=True)
        results[model] = (x, y, e)
        sol.save(OUT / f"hi_{model}.npz")
        np.save(OUT / f"strain_{model}.npy", e)
    print("wrote", visualize(results, OUT / "strains_hi.png"))
    for model, r in results.items():
        visualize({model: r}, OUT / f"strain_{model}.png")
    return 0


if __name__ == "__main__":
    rc = main()
    if rc:  # exit only on failure: the docs gallery runs the demos in its own process
        sys.exit(rc)
