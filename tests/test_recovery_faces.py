"""A shear band's faces and the strain recovery (docs/refinement.md, "The strain recovery at a shear band's
faces"): the element strain keeps the band's step only where its faces lie on rows of mesh nodes."""
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.fields import element_strains, recovered_strains

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

H = 1.0 / 3.0                      # the refined rows of a band under L7 (0.33 mm)
SLIDE, THICK = 0.2, 1.0            # mm


def _band_errors(top):
    """Relative L2 e_xy error along depth (2-8 mm) of the element strain and the nodal average, for the exact
    displacement of a band of faces ``top`` and ``top + THICK`` on a tensor mesh of rows ``H``."""
    xs = np.linspace(0.0, 10.0, 31)
    m = MeshQuad1.init_tensor(xs, np.linspace(0.0, 4.0, 5))
    p, t = m.p, m.t
    u = np.zeros(2 * p.shape[1])
    u[1::2] = SLIDE * np.clip((p[0] - top) / THICK, 0.0, 1.0)
    xf = np.linspace(2.0, 8.0, 6001)
    true = np.where((xf > top) & (xf < top + THICK), SLIDE / (2 * THICK), 0.0)
    e = element_strains(p, t, u)[:, 2]
    cx = p[0][t].mean(axis=0)
    rows = np.array([e[np.isclose(cx, c)].mean() for c in 0.5 * (xs[1:] + xs[:-1])])
    el = rows[np.clip(np.searchsorted(xs, xf) - 1, 0, rows.size - 1)]
    ns = recovered_strains(p, t, u, "average")[:, 2]
    rec = np.interp(xf, xs, [ns[np.isclose(p[0], x)].mean() for x in xs])
    rel = lambda a: float(np.sqrt(np.sum((a - true) ** 2) / np.sum(true ** 2)))  # noqa: E731
    return rel(el), rel(rec)


def test_element_strain_keeps_the_step_only_with_faces_on_rows():
    # measured: faces on rows 0.032 (the step's sampling on the 0.001 mm line) / average 0.334;
    # faces mid-row 0.408 / 0.354
    el_on, avg_on = _band_errors(4.0)
    el_mid, avg_mid = _band_errors(4.0 + H / 2)
    assert el_on < 0.1
    assert avg_on > 0.25 > el_on
    assert el_mid > avg_mid
    assert el_mid > 5 * el_on


def test_benchmark_split_elements_and_face_offsets():
    from benchmarks.recovery_faces import face_offsets, split_elements

    xs = np.concatenate([[0.0, 1.0, 2.0], np.arange(1, 7) * H + 2.0, [5.0, 6.0]])
    m = MeshQuad1.init_tensor(xs, np.linspace(0.0, 3.0, 4))
    res = types.SimpleNamespace(mesh=m, refinement=types.SimpleNamespace(base_size=(1.0, 1.0)))
    split = split_elements(res)
    cx = m.p[0][m.t].mean(axis=0)
    assert np.array_equal(split, (cx > 2.0) & (cx < 4.0))
    band = types.SimpleNamespace(depth_mm=3.0, thickness_mm=1.0)
    # faces 2.5 and 3.5 mm; rows at 2 + k/3 mm: 2.333 and 2.667, 3.333 and 3.667
    assert face_offsets(res, band) == pytest.approx((1.0 / 6.0, 1.0 / 6.0))
