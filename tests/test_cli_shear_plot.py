"""``femreg plot RESULT --reference FILE --shear``: the shear-strain product (e_xy per element, its predicted
precision and the element's width in lateral speckle cells, femreg.shear.shear_strain_map) as a picture from the
command line."""
import numpy as np
import pytest

from femreg.cli import main


@pytest.fixture(scope="module")
def band_files(tmp_path_factory):
    """A 1 mm band sliding 0.15 mm at 8 mm under L7 (1 % compression), registered by the CLI with --refine slip."""
    from forward import fields as F
    from forward.pairs import make_pair

    d = make_pair(F.ShearBand(8.0, 1.0, 0.15, 0.01), "L7", (16.0, 12.0), 30.0, 0)
    tmp = tmp_path_factory.mktemp("band")
    np.save(tmp / "a.npy", d.ref.astype(np.float32))
    np.save(tmp / "b.npy", d.mov.astype(np.float32))
    sp = [str(v) for v in d.spacing]
    assert main(["register", str(tmp / "a.npy"), str(tmp / "b.npy"), "--spacing", *sp, "--refine", "slip",
                 "--origin", *[str(v) for v in d.origin],
                 "--no-progress", "-o", str(tmp / "pair.npz")]) == 0
    return tmp, sp, d


def test_shear_figure_is_written_and_draws_the_band(band_files, capsys):
    import femreg
    from femreg.shear import narrow_elements, shear_strain_map

    tmp, sp, d = band_files
    capsys.readouterr()
    assert main(["plot", str(tmp / "pair.npz"), "--reference", str(tmp / "a.npy"), "--spacing", *sp, "--shear",
                 "-o", str(tmp / "pair.png")]) == 0
    out = capsys.readouterr().out
    png = tmp / "pair_shear.png"
    assert png.is_file() and png.stat().st_size > 20_000
    assert "pair_shear.png" in out and "relative predicted precision" in out
    # the map it draws: e_xy of the band (true 7.5 %) far above e_xy away from it; the count it prints is the
    # map's own (the L7 beam's lateral speckle cell, about 1.2 mm, is wider than the 0.6 mm default columns)
    res = femreg.load_result(tmp / "pair.npz")
    sm = shear_strain_map(res, d.ref)
    xc = res.mesh.p[0][res.mesh.t].mean(axis=0)
    band, far = np.abs(xc - 8.0) < 0.5, np.abs(xc - 8.0) > 3.0
    assert band.any() and far.any()
    assert np.median(sm["exy"][band]) > 0.04, np.median(sm["exy"][band])
    assert np.median(np.abs(sm["exy"][far])) < np.median(sm["exy"][band]) / 5
    narrow = int(out.split("mm; ")[1].split(" of ")[0])
    assert narrow == int(np.sum(narrow_elements(sm))) and narrow > 0
    assert np.all(np.isfinite(sm["sigma"]) & (sm["sigma"] > 0))


def test_shear_figure_needs_the_reference(band_files, capsys):
    tmp, sp, _ = band_files
    capsys.readouterr()
    assert main(["plot", str(tmp / "pair.npz"), "--shear", "-o", str(tmp / "p2.png")]) == 2
    err = capsys.readouterr().err
    assert "--shear needs --reference" in err and "Traceback" not in err


def test_shear_figure_refuses_a_result_without_element_quality(band_files, capsys):
    tmp, sp, _ = band_files
    with np.load(tmp / "pair.npz", allow_pickle=False) as z:
        kept = {k: z[k] for k in z.files if k != "quality"}
    np.savez(tmp / "noq.npz", **kept)
    capsys.readouterr()
    assert main(["plot", str(tmp / "noq.npz"), "--reference", str(tmp / "a.npy"), "--spacing", *sp, "--shear",
                 "-o", str(tmp / "noq.png")]) == 2
    err = capsys.readouterr().err
    assert "per-element quality" in err and "Traceback" not in err
