"""`femreg measure`: SR, CNR_e, SNR_e of a known field against the same statistics computed here independently
(Gauss points of the bilinear field by hand), the modulus contrast of an inversion, JSON, and the exit codes."""
import json

import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.cli import main
from femreg.registration import RegistrationResult

from _round_inclusion import exx_true, nodal_u

C, R = (10.0, 0.0), 4.0
H = 1.0


@pytest.fixture(scope="module")
def field():
    m = MeshQuad1.init_tensor(np.arange(0, 20.01, H), np.arange(-10, 10.01, H))
    return m, nodal_u(m.p)


def _save(tmp_path, m, u, name="r.npz", **kw):
    res = RegistrationResult(m, u, shape=(81, 81), spacing=(0.25, 0.25), origin=(0.0, -10.0),
                             **dict(dict(success=True, message="converged"), **kw))
    return res.save(tmp_path / name)


def _gauss_exx(m, u):
    """Axial strain of the bilinear field at 3 x 3 Gauss points of each (axis-aligned) element, with the points
    and weights: d ux / dx = ((u10 - u00)(1 - s) + (u11 - u01) s) / hx, s the lateral reference coordinate."""
    g, gw = np.polynomial.legendre.leggauss(3)
    g, gw = (g + 1) / 2, gw / 2
    P = m.p[:, m.t]                                             # (2, 4, n_el), corners in any order
    x0, y0 = P[0].min(axis=0), P[1].min(axis=0)
    hx, hy = P[0].max(axis=0) - x0, P[1].max(axis=0) - y0
    corner = (P[0] > x0 + hx / 2).astype(int) + 2 * (P[1] > y0 + hy / 2)      # 0 (x0,y0) 1 (x1,y0) 2 (x0,y1) 3
    uxe = u[0::2][m.t]
    el = np.arange(m.t.shape[1])
    ux = np.array([uxe[np.argmax(corner == k, axis=0), el] for k in range(4)])   # (4, n_el) by corner
    pts, w, e = [], [], []
    for a, wa in zip(g, gw):          # axial reference coordinate
        for b, wb in zip(g, gw):      # lateral
            e.append(((ux[1] - ux[0]) * (1 - b) + (ux[3] - ux[2]) * b) / hx)
            pts.append(np.column_stack([x0 + a * hx, y0 + b * hy]))
            w.append(wa * wb * hx * hy)
    return np.concatenate(pts), np.concatenate(w), np.concatenate(e)


def _stats(e, w, inside, background):
    def mv(s):
        m = np.sum(w[s] * e[s]) / np.sum(w[s])
        return m, np.sum(w[s] * (e[s] - m) ** 2) / np.sum(w[s])
    (ea, va), (eb, vb) = mv(background), mv(inside)
    return {"SR": ea / eb, "CNR_e": 2 * (ea - eb) ** 2 / (va + vb), "SNR_e": abs(ea) / np.sqrt(va)}


def test_measure_matches_independent_statistics_and_the_truth(tmp_path, field, capsys):
    m, u = field
    path = _save(tmp_path, m, u)
    out = tmp_path / "m.json"
    assert main(["measure", str(path), "--inclusion", "10", "0", "4", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    got = json.loads(out.read_text())
    pts, w, e = _gauss_exx(m, u)
    inside = np.hypot(pts[:, 0] - C[0], pts[:, 1] - C[1]) < R
    want = _stats(e, w, inside, ~inside)
    for k in ("SR", "CNR_e", "SNR_e"):
        assert got[k] == pytest.approx(want[k], rel=1e-9), k
        assert f"{got[k]:.4g}" in printed
    assert got["success"] and not got["flagged"] and got["kind"] == "registration"
    # and near the field's own ratio (background -1 %, inclusion -0.4 %: 2.5; the mesh smooths the edge)
    assert 2.1 < got["SR"] < 2.5, got["SR"]
    # a background rectangle: only its part outside the disk is the background
    assert main(["measure", str(path), "--inclusion", "10", "0", "4", "--background", "2", "8", "-9", "9",
                 "-o", str(out)]) == 0
    got = json.loads(out.read_text())
    bg = ~inside & (pts[:, 0] >= 2) & (pts[:, 0] <= 8) & (pts[:, 1] >= -9) & (pts[:, 1] <= 9)
    want = _stats(e, w, inside, bg)
    for k in ("SR", "CNR_e", "SNR_e"):
        assert got[k] == pytest.approx(want[k], rel=1e-9), k


def test_measure_failed_result_exit_1_with_numbers(tmp_path, field, capsys):
    m, u = field
    path = _save(tmp_path, m, u, success=False, message="peak hopping remains")
    out = tmp_path / "f.json"
    assert main(["measure", str(path), "--inclusion", "10", "0", "4", "--json", str(out)]) == 1
    cap = capsys.readouterr()
    assert "FLAGGED" in cap.out and "peak hopping remains" in cap.out and "strain ratio" in cap.out
    got = json.loads(out.read_text())
    assert got["flagged"] and np.isfinite(got["SR"])


def test_measure_bad_input_exit_2_with_the_valid_bounds(tmp_path, field, capsys):
    m, u = field
    path = _save(tmp_path, m, u)
    assert main(["measure", str(path), "--inclusion", "40", "0", "3"]) == 2
    err = capsys.readouterr().err
    assert "outside the mesh" in err and "x 0.00 to 20.00 mm" in err and "y -10.00 to 10.00 mm" in err
    assert main(["measure", str(path), "--inclusion", "10", "0", "-1"]) == 2
    assert main(["measure", str(path), "--inclusion", "10", "0", "3", "--background", "30", "40", "0", "5"]) == 2
    assert "does not overlap" in capsys.readouterr().err
    assert main(["measure", str(path), "--inclusion", "10", "0", "3", "--json", str(tmp_path / "x.txt")]) == 2
    assert main(["measure", str(tmp_path / "missing.npz"), "--inclusion", "10", "0", "3"]) == 2


def test_measure_inversion_modulus_contrast(tmp_path, field, capsys):
    from femreg.inversion import InversionResult

    m, u = field
    c = m.p[:, m.t].mean(axis=1)
    inc = np.hypot(c[0] - C[0], c[1] - C[1]) < R
    mu = np.where(inc, 3.0, 1.0)
    inv = InversionResult(mesh=m, mu=mu, model="plane-stress", lambda_bar=2.0, beta=0.01, u_measured=u,
                          success=True, message="ok")
    inv.save(tmp_path / "mu.npz")
    out = tmp_path / "mu.json"
    assert main(["measure", str(tmp_path / "mu.npz"), "--inclusion", "10", "0", "4", "-o", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["kind"] == "inversion"
    # elements wholly inside the disk are 3, wholly outside 1 (the cut ones are left out): contrast 3 exactly
    assert got["modulus_contrast"] == pytest.approx(3.0, rel=1e-12)
    assert "modulus contrast" in capsys.readouterr().out
    # the strain numbers come from the inversion's displacement, as for the registration
    reg = _save(tmp_path, m, u)
    assert main(["measure", str(reg), "--inclusion", "10", "0", "4", "-o", str(tmp_path / "r.json")]) == 0
    assert got["SR"] == pytest.approx(json.loads((tmp_path / "r.json").read_text())["SR"], rel=1e-12)


def test_modulus_contrast_uncertainty_first_order(field):
    """Uniform modulus in each region and equal element areas: each element's share of its region is 1/n, so
    sd(log contrast) = sigma sqrt(1/n_in + 1/n_out) -- and the estimate grows with sigma."""
    from femreg.cli.measure_cmd import _modulus, _regions
    from femreg.inversion import InversionResult

    m, u = field
    inv = InversionResult(mesh=m, mu=np.ones(m.t.shape[1]), model="plane-stress", lambda_bar=2.0, beta=0.01,
                          u_measured=u, success=True)
    roi, _ = _regions((10.0, 0.0, 4.0), None)
    node_in = roi(m.p.T)[m.t]
    n_in, n_out = int(node_in.all(axis=0).sum()), int((~node_in).all(axis=0).sum())
    assert "contrast_sd_log" not in _modulus(inv, roi, None)
    inv.uncertainty = np.full(m.t.shape[1], 0.2)
    got = _modulus(inv, roi, None)
    assert got["contrast"] == pytest.approx(1.0)
    assert got["contrast_sd_log"] == pytest.approx(0.2 * np.sqrt(1 / n_in + 1 / n_out), rel=1e-12)


def test_measure_flagged_inversion_said_once_and_unknown_spread_in_words(tmp_path, field, capsys):
    from femreg.inversion import InversionResult

    m, u = field
    inv = InversionResult(mesh=m, mu=np.ones(m.t.shape[1]), model="plane-stress", lambda_bar=2.0, beta=0.1,
                          u_measured=u, success=False, message="FLAGGED: beta 0.1 is at the large edge of its grid")
    inv.uncertainty = np.full(m.t.shape[1], 0.2)
    inv.uncertainty[0] = np.nan                                       # an element the data do not constrain
    inv.save(tmp_path / "mu.npz")
    assert main(["measure", str(tmp_path / "mu.npz"), "--inclusion", "10", "0", "4"]) == 1
    cap = capsys.readouterr()
    assert cap.out.count("FLAGGED") == 1 and "the inversion is flagged (beta 0.1 is at the large edge" in cap.out
    assert "spread unknown: the data do not constrain some of the elements measured" in cap.out
    assert "nan" not in cap.out.lower()
    assert cap.err.strip() == ("femreg measure: the result is a flagged inversion: beta 0.1 is at the large edge "
                               "of its grid")
