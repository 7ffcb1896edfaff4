"""``femreg measure --slide X0 X1``: the lateral slide across a sliding interface (fascia over muscle), read from a
result's displacement; exact for a field the mesh represents exactly."""
from __future__ import annotations

import json

import numpy as np
import pytest

from femreg.cli import main
from femreg.io import save_result
from forward.fields import ShearBand


def _band_result(path, slide=0.025, success=True):
    """A result on a 20 x 25 mm mesh (0.5 mm elements) holding a ShearBand (1 mm at 10 mm, 0.8 % compression)
    whose band edges are element edges: the bilinear displacement is exact."""
    x, y = np.meshgrid(np.arange(1.0, 21.01, 0.5), np.arange(0.0, 25.01, 0.5), indexing="ij")
    p = np.vstack([x.ravel(), y.ravel()])
    idx = np.arange(p.shape[1]).reshape(x.shape)
    t = np.vstack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()])
    band = ShearBand(10.0, 1.0, slide, 0.008)
    u = band.displacement(p.T).ravel()
    shape = (60, 50)
    grid = {k: np.zeros(shape) for k in ("ux", "uy", "exx", "eyy", "exy")}
    save_result(path, dict(mesh_points=p, mesh_cells=t, u=u, spacing=np.array([0.35, 0.5]), origin=np.zeros(2),
                           shape=np.array(shape), regularizer="strain", alpha=0.5, success=success, nit=4,
                           message="converged" if success else "FAILED: images do not match", ncc_before=0.3,
                           ncc_after=0.9, energy_history=np.array([3.0, 2.0, 1.0]), **grid))
    return band


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_slide_across_the_band(tmp_path, capsys):
    band = _band_result(tmp_path / "r.npz")
    rc, out, err = _run(["measure", tmp_path / "r.npz", "--slide", 8, 12, "--json", tmp_path / "m.json"], capsys)
    assert rc == 0, err
    s = json.loads((tmp_path / "m.json").read_text())["slide"]
    assert s["slide_mm"] == pytest.approx(band.slide_mm, abs=1e-9)      # exact: the field is bilinear per element
    assert s["slide_iqr_mm"] < 1e-9 and "slide (lateral u_y at 12 mm minus at 8 mm" in out, out
    # both depths above the band: no slide; a lateral span limits the rows
    rc, out, _ = _run(["measure", tmp_path / "r.npz", "--slide", 3, 8, "--lateral", 5, 20, "-o", tmp_path / "n.json"],
                      capsys)
    n = json.loads((tmp_path / "n.json").read_text())["slide"]
    assert rc == 0 and abs(n["slide_mm"]) < 1e-9 and n["lateral_mm"] == [5.0, 20.0]
    # with --inclusion too: both reports
    rc, out, _ = _run(["measure", tmp_path / "r.npz", "--inclusion", 15, 12, 2, "--slide", 8, 12], capsys)
    assert rc == 0 and "strain ratio SR" in out and "slide (lateral" in out


def test_slide_refusals_and_a_failed_result(tmp_path, capsys):
    _band_result(tmp_path / "r.npz")
    for argv, needle in ((["--slide", 12, 8], "increasing depths"),
                         (["--slide", 8, 30], "outside the mesh"),
                         (["--slide", 8, 12, "--lateral", 5, 40], "inside the mesh"),
                         (["--lateral", 5, 20, "--inclusion", 15, 12, 2], "--lateral qualifies --slide"),
                         ([], "--inclusion X Y R")):
        rc, _, err = _run(["measure", tmp_path / "r.npz", *argv], capsys)
        assert rc == 2 and needle in err, (argv, err)
    _band_result(tmp_path / "f.npz", success=False)
    rc, out, err = _run(["measure", tmp_path / "f.npz", "--slide", 8, 12], capsys)
    assert rc == 1 and "slide (lateral" in out and "failed" in err, (out, err)
