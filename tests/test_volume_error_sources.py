"""The error split of benchmarks/volume_error_sources.py: its parts add up to the total, and its linear strain
recovery is exact for a linear strain on a graded tensor mesh (where femreg's plain nodal average is not)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _mod():
    sys.path.insert(0, str(REPO / "benchmarks"))
    spec = importlib.util.spec_from_file_location("volume_error_sources",
                                                  REPO / "benchmarks" / "volume_error_sources.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_split_parts_add_up_to_the_total():
    mod = _mod()
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(0, 72, 4000), rng.uniform(-22, 22, 4000)])
    w = rng.uniform(0.5, 1.5, q.shape[0])
    et = rng.normal(size=(q.shape[0], 3))
    em = et + 0.1 * rng.normal(size=et.shape)
    masks = mod.regions(q, 1.5)
    assert sum(m.astype(int) for m in masks.values()).max() == 1          # the regions do not overlap
    s = mod.split(w, em, et, masks)
    parts = sum(s[k]["all"] ** 2 for k in masks if masks[k].any())
    covered = np.any(np.column_stack(list(masks.values())), axis=1)
    assert covered.all()
    assert np.isclose(parts, s["e"] ** 2, rtol=1e-12)
    assert np.isclose(sum(v ** 2 for v in s["components"].values()), s["e"] ** 2, rtol=1e-12)


def test_linear_recovery_exact_on_a_graded_mesh():
    from skfem import MeshHex1

    from femreg.volume_fields import recovered_strains_3d

    mod = _mod()
    ax = np.array([0.0, 2.0, 2.5, 3.0, 5.0, 7.0])            # 2 mm slabs beside 0.5 mm ones
    mesh = MeshHex1.init_tensor(ax, np.array([0.0, 1.0, 3.0, 3.5]), np.array([0.0, 2.0, 2.5, 4.5]))
    x, y, z = mesh.p
    # u_x = x^2 / 2: e_xx = x, linear; u_y, u_z = 0
    u = np.zeros(3 * mesh.p.shape[1])
    u[0::3] = 0.5 * x ** 2
    inner = (x > 0) & (x < 7)                                # the recovery's boundary nodes take their cell's value
    lin = mod.linear_recovery(mesh, u)[:, 0]
    avg = recovered_strains_3d(mesh, u)[:, 0]
    assert np.allclose(lin[inner], x[inner], atol=1e-12)
    # the plain average is off where a 2 mm slab meets a 0.5 mm one (x = 2: (1 + 2.25) / 2 = 1.625, not 2)
    assert np.max(np.abs(avg[inner] - x[inner])) > 0.3
