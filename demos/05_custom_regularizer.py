r"""Demo 05: write your own regulariser in a few lines
==================================================

This demo shows how to

* turn a weak form into a regulariser (FEniCSx style): a *Poisson-ratio link* that asks the lateral strain to
  follow the axial strain of an incompressible plane-stress solid,
  :math:`R[u] = \tfrac{\alpha}{2}\int_\Omega \nabla^s u : \nabla^s u
  + \tfrac{\beta}{2}\int_\Omega (\varepsilon_{yy} + \nu\,\varepsilon_{xx})^2`, :math:`\nu = 1/2`;
* write a total-variation regulariser as a weak form too: the jumps of the lateral strain across the edges
  between neighbouring elements, :math:`R[u] = \alpha\sum_j l_j\sqrt{[\![\varepsilon_{yy}]\!]_j^2 + \delta}`
  (a piecewise-constant lateral-strain prior, eq:dmreg2 with a user quantity);
* pass either to ``femreg.register`` and compare the lateral displacement error with R_eps and the built-in
  momentum regulariser R_P_sigma on a synthetic pair warped by a plane-stress FE solution with a stiff inclusion.

Output: ``out/05_custom_regularizer/`` (a table of errors and a figure of the lateral displacement).
Run: ``python demos/05_custom_regularizer.py [--quick]``.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np
from skfem import BilinearForm, LinearForm
from skfem.helpers import ddot, sym_grad

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout, not an installed copy
import femreg  # noqa: E402
import forward  # noqa: E402
from femreg.regularizers import from_forms, from_jump_forms  # noqa: E402
from femreg.synthetic import speckle_pair  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--quick", action="store_true", help="smaller image around the inclusion")
args = ap.parse_args()
out = Path("out/05_custom_regularizer")
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## 1. A quadratic regulariser from weak forms
# Write :math:`a(u, v)` with ``skfem.helpers`` exactly as for a scikit-fem solve.  Axis convention: index 0 is
# axial (x, depth), 1 is lateral (y).

# %%
NU = 0.5   # incompressible plane stress: eps_yy = -nu eps_xx under uniaxial load


@BilinearForm
def strain_energy(u, v, w):
    return ddot(sym_grad(u), sym_grad(v))


@BilinearForm
def poisson_link(u, v, w):
    eu, ev = sym_grad(u), sym_grad(v)
    return (eu[1, 1] + NU * eu[0, 0]) * (ev[1, 1] + NU * ev[0, 0])


def poisson_regularizer(alpha, beta_over_alpha=10.0):
    return from_forms([(strain_energy, 1.0, "gauss3"), (poisson_link, beta_over_alpha, "centre")],
                      alpha=alpha, name="user-poisson-link")


# %% [markdown]
# ## 2. A TV regulariser from a weak form
# Write the quantity whose jumps across interior edges are penalised as a ``LinearForm`` in the test function
# (here the lateral strain); ``from_jump_forms`` evaluates it on both sides of every edge (scikit-fem's
# ``InteriorFacetBasis``), weights by the edge lengths, and gives gradient and lagged-diffusivity Hessian
# (eq:dmreg3, eq:dmreg4).  The built-in momentum regularisers are the same construction with the two components
# of A[u] n (eq:meq).  Data reach the form through ``w`` (here a scale).

# %%
@LinearForm
def lateral_strain(v, w):
    return w.scale * sym_grad(v)[1, 1]


def lateral_tv_regularizer(alpha):
    return from_jump_forms([lateral_strain], alpha=alpha, scale=1.0, name="user-lateral-strain-tv")


# %% [markdown]
# ## 3. A synthetic pair: plane-stress FE field with a stiff inclusion (forward/), speckle warped by it

# %%
t0 = time.perf_counter()
sol = forward.solve_elasticity("plane-stress", inclusion_modulus=40.0, poisson=0.495, compression_mm=1.0,
                               mesh_size_mm=1.0, refine_region_mm=(80.0, 26.0))
spacing = (0.0192, 0.3)
x0, Lx, Ly = (15.0, 30.0, 24.0) if args.quick else (0.0, 72.0, 44.0)
shape = (int(round(Lx / spacing[0])), int(round(Ly / spacing[1])) + 1)
origin = (x0, -(shape[1] - 1) * spacing[1] / 2)
# sample the FE field once on a fine grid; the warp then interpolates (fast, smooth)
from scipy.interpolate import RegularGridInterpolator  # noqa: E402

gx = np.arange(max(x0 - 3, 0.0), x0 + Lx + 3, 0.05)
gy = np.arange(-Ly / 2 - 3, Ly / 2 + 3, 0.15)
U = sol.displacement(np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)).reshape(len(gx), len(gy), 2)
field = RegularGridInterpolator((gx, gy), U, method="linear", bounds_error=False, fill_value=None)
reference, moving = speckle_pair(lambda p: field(np.asarray(p, float)), shape=shape, spacing=spacing,
                                 origin=origin, seed=1, snr_db=20)
print(f"pair {shape} px built in {time.perf_counter() - t0:.1f} s")

# %% [markdown]
# ## 4. Register with each regulariser (a small alpha sweep each) and compare lateral errors

# %%
candidates = {
    "R_eps (built-in 'strain')": [("strain", a) for a in (1.0, 3.0, 10.0)],
    "R_P_sigma (built-in 'momentum-stress')": [("momentum-stress", a) for a in (0.03, 0.1, 0.3)],
    "user Poisson link (BilinearForms)": [(poisson_regularizer(a), None) for a in (1.0, 3.0, 10.0)],
    "user lateral-strain TV (jump form)": [(lateral_tv_regularizer(a), None) for a in (0.03, 0.1, 0.3)],
}


def errors(res):
    nodes = res.mesh.p.T
    true = sol.displacement(nodes)
    meas = np.column_stack([res.u[0::2], res.u[1::2]])
    return [np.linalg.norm(meas[:, k] - true[:, k]) / np.linalg.norm(true[:, k]) for k in (0, 1)]


lines = [f"{'regulariser':42s} {'alpha':>8s} {'axial err %':>12s} {'lateral err %':>14s} {'s':>6s}"]
best = {}
for label, runs in candidates.items():
    for reg, alpha in runs:
        t = time.perf_counter()
        res = femreg.register(reference, moving, spacing=spacing, origin=origin, regularizer=reg, alpha=alpha)
        ex, ey = errors(res)
        lines.append(f"{label:42s} {res.alpha:8.3g} {100 * ex:12.2f} {100 * ey:14.1f} {time.perf_counter() - t:6.1f}")
        if label not in best or ey < best[label][0]:
            best[label] = (ey, res)
print("\n".join(lines))
(out / "errors.txt").write_text("\n".join(lines) + "\n")

# %% [markdown]
# ## 5. Lateral displacement at each regulariser's best alpha

# %%
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

grid = best[next(iter(best))][1].pixel_points()
true_uy = sol.displacement(grid)[:, 1].reshape(shape)
fig, axes = plt.subplots(1, len(best) + 1, figsize=(3 * (len(best) + 1), 4.5), sharey=True)
ext = (origin[1], origin[1] + (shape[1] - 1) * spacing[1], origin[0] + (shape[0] - 1) * spacing[0], origin[0])
lim = np.nanmax(np.abs(true_uy))
axes[0].imshow(true_uy, extent=ext, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
axes[0].set_title("true u_y (FE)")
for ax, (label, (ey, res)) in zip(axes[1:], best.items()):
    ax.imshow(res.on_grid()["uy"], extent=ext, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
    ax.set_title(f"{label.split(' (')[0]}\nlateral err {100 * ey:.0f} %", fontsize=8)
axes[0].set_ylabel("depth x (mm)")
for ax in axes:
    ax.set_xlabel("lateral y (mm)")
fig.tight_layout()
fig.savefig(out / "lateral_displacement.png", dpi=120)
print(f"wrote {out / 'errors.txt'} and {out / 'lateral_displacement.png'}")
for label, (ey, res) in best.items():
    print(f"best {label:42s} lateral error {100 * ey:5.1f} % at alpha {res.alpha:g}")
