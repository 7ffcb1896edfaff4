"""3D modulus results from the command line and in pictures: ``femreg invert`` on a volume's registration result
(six-number region, seven-number reference, exit codes 0 / 1 / 2), the file round trip, ``femreg plot --slice``
(three orthogonal slices of the modulus, its uncertainty and the axial strain: panels, labels, values, layout)
and ``femreg measure`` with a sphere.

The displacement fields are exact elasticity solutions (two layers in series, as tests/test_inversion3d.py) on a
hexahedral mesh, or a small registered RF volume (tests/_volumes.py) for the whole chain.
"""
from __future__ import annotations

import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import femreg  # noqa: E402
from femreg.cli import main  # noqa: E402
from femreg.errors import InputError  # noqa: E402
from femreg.inversion import InversionResult, _tensor_mesh_3d, load_inversion  # noqa: E402
from femreg.volume_result import VolumeResult  # noqa: E402

BOX = (0.0, 12.0, -3.0, 3.0, -3.0, 3.0)


def _layers(ratio=2.0, x_int=6.0):
    """Two layers in series along x, mu = 1 then ``ratio``: an exact solution (tests/test_inversion3d.py)."""
    def f(p):
        x = p[:, 0]
        s = np.where(x < x_int, x, x_int + (x - x_int) / ratio)
        return np.column_stack([-0.01 * s, 0.004 * s, -0.003 * s])
    return f


def _volume_result(path, success=True, message="converged"):
    mesh = _tensor_mesh_3d(BOX, (1.5, 2.0, 2.0))
    res = VolumeResult(mesh, _layers()(mesh.p.T).ravel(), shape=(61, 31, 31), spacing=np.full(3, 0.2),
                       origin=np.array([0.0, -3.0, -3.0]), success=success, status=0 if success else 1,
                       message=message)
    res.save(path)
    return path


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def inverted(tmp_path_factory):
    """A volume's registration result, inverted once by the CLI with --png, --vtu and a reference box."""
    d = tmp_path_factory.mktemp("inv3d")
    vol = _volume_result(d / "vol.npz")
    argv = ["invert", vol, "-o", d / "mu.npz", "--png", d / "mu.png", "--reference", 0, 6, -3, 3, -3, 3, 10]
    try:
        import meshio  # noqa: F401

        argv += ["--vtu", d / "mu.vtu"]
    except ImportError:
        pass
    rc = main([str(a) for a in argv])
    return d, vol, rc


def test_cli_inverts_a_volume_result_and_writes_its_files(inverted):
    d, vol, rc = inverted
    assert rc == 0
    res = load_inversion(d / "mu.npz")
    assert res.dim == 3 and res.model == "3d" and res.mesh.t.shape == (8, 8 * 3 * 3)
    c = res.centroids[:, 0]
    contrast = res.mu[c > 6].mean() / res.mu[c < 6].mean()
    # the layers' modulus ratio is 2; measured 1.99 on this 1.5 x 2 x 2 mm mesh (the default beta rule); 5 %
    assert abs(contrast / 2.0 - 1.0) < 0.05, contrast
    # the reference box (x 0-6 mm) holds E = 10 kPa: the shear modulus there is 10 / 3 kPa on average
    ref = c < 6
    assert np.mean(res.youngs_modulus_kpa[ref]) == pytest.approx(10.0, rel=0.02)
    assert (d / "mu.png").stat().st_size > 20_000
    assert res.uncertainty is not None and res.constrained.all()
    if (d / "mu.vtu").exists():
        import meshio

        m = meshio.read(d / "mu.vtu")
        assert np.allclose(m.cell_data["shear_modulus"][0], res.mu)


def test_volume_inversion_file_round_trip(tmp_path):
    reg = femreg.load_result(_volume_result(tmp_path / "vol.npz"))
    res = femreg.invert(reg, beta=1e-3, reference=((0.0, 6.0, -3.0, 3.0, -3.0, 3.0), 12.0))
    res.constrained[:2] = False                       # a mask with both values survives the file
    res.uncertainty[:2] = np.nan
    back = load_inversion(res.save(tmp_path / "mu.npz"))
    assert back.dim == 3 and type(back.mesh).__name__ == "MeshHex1"
    assert np.array_equal(back.mesh.p, res.mesh.p) and np.array_equal(back.mesh.t, res.mesh.t)
    for key in ("mu", "u_measured", "u_model", "strain_measured", "history", "shear_modulus_kpa", "uncertainty",
                "constrained"):
        assert np.array_equal(getattr(back, key), getattr(res, key), equal_nan=key != "constrained"), key
    for key in ("model", "lambda_bar", "beta", "beta_rule", "regularization", "weights", "success", "message",
                "flags", "nit", "strain_ratio", "misfit"):
        assert getattr(back, key) == (pytest.approx(getattr(res, key), nan_ok=True)
                                      if isinstance(getattr(res, key), float) else getattr(res, key)), key
    # 3D weights: the defaults (1, 0.1, 0.01), lowered by the data's noise; three of them, saved as computed
    assert back.strain_components == res.strain_components and len(back.weights) == 3
    assert back.weights[0] == 1.0 and back.weights[2] <= 0.01 and back.weights == res.weights
    # the reloaded result draws as the original does
    fa, fb = res.plot(), back.plot()
    ia = [a.images[0].get_array() for a in fa.axes if a.images]
    ib = [a.images[0].get_array() for a in fb.axes if a.images]
    assert len(ia) == len(ib) == 9
    assert all(np.array_equal(np.ma.filled(a, -1.0), np.ma.filled(b, -1.0)) for a, b in zip(ia, ib))
    plt.close("all")


@pytest.mark.parametrize("extra, words", [
    (["--region", 0, 12, -2, 2], "--region takes 6 numbers (X0 X1 Y0 Y1 Z0 Z1, mm) for a volume's result, got 4"),
    (["--reference", 0, 6, -3, 3, 10], "--reference takes 7 numbers"),
    (["--region", 0, 12, 2, -2, -2, 2], "y0 < y1"),
    (["--model", "plane-stress"], "is a 2D model"),
    (["--element-size", 1, 2], "--element-size takes 1 or 3 values"),
    (["--slice", "middle"], "--slice takes X Y Z (mm) or one of centre, stiffest, softest"),
    (["--images", "a.npz", "b.npz"], "a.npz: not a volume file"),
])
def test_cli_invert_volume_bad_input_exits_2_with_one_line(tmp_path, capsys, extra, words):
    vol = _volume_result(tmp_path / "vol.npz")
    rc, out, err = _run(["invert", vol, "-o", tmp_path / "mu.npz", *extra], capsys)
    assert rc == 2 and words in err and err.count("\n") == 1, err
    assert not (tmp_path / "mu.npz").exists()


def test_cli_invert_failed_volume_registration_is_refused_or_flagged(tmp_path, capsys):
    vol = _volume_result(tmp_path / "vol.npz", success=False, message="FAILED: ncc 0.1 after registration")
    rc, _, err = _run(["invert", vol, "-o", tmp_path / "mu.npz"], capsys)
    assert rc == 2 and "failed registration" in err and not (tmp_path / "mu.npz").exists()
    rc, _, err = _run(["invert", vol, "-o", tmp_path / "mu.npz", "--allow-failed", "--no-uncertainty"], capsys)
    assert rc == 1 and "FLAGGED" in err
    res = load_inversion(tmp_path / "mu.npz")
    assert not res.success and "failed registration" in res.message
    # its picture carries the red banner
    fig = res.plot()
    assert fig.get_suptitle().startswith("INVERSION FAILED: inverted from a failed registration")
    plt.close(fig)


def _sphere_result(success=True, with_uncertainty=True):
    """A 3D inversion result made by hand: mu = 3 in the elements whose centre lies within 3 mm of (8.5, 1.5, -0.5)
    mm, 1 elsewhere, on a 16 x 12 x 10 mm box of 1 mm cubes; u_measured a uniform 1 % compression; the
    uncertainty NaN (not constrained) in the 4 elements of the deepest corner."""
    mesh = _tensor_mesh_3d((0.0, 16.0, -6.0, 6.0, -5.0, 5.0), (1.0, 1.0, 1.0))
    c = mesh.p[:, mesh.t].mean(axis=1).T
    inside = np.sum((c - [8.5, 1.5, -0.5]) ** 2, axis=1) < 9.0
    mu = np.where(inside, 3.0, 1.0)
    u = np.column_stack([-0.01 * mesh.p[0], 0.005 * mesh.p[1], 0.005 * mesh.p[2]]).ravel()
    res = InversionResult(mesh=mesh, mu=mu, model="3d", lambda_bar=99.0, beta=0.01, u_measured=u, success=success,
                          message="ok" if success else "FLAGGED: beta 0.0001 is the smallest value of its grid")
    if with_uncertainty:
        corner = (c[:, 0] > 15) & (c[:, 1] > 4) & (c[:, 2] > 3)
        res.uncertainty = np.where(corner, np.nan, 0.05 + 0.01 * c[:, 0])
        res.constrained = ~corner
    return res, inside, c


def _panels(fig):
    return [a for a in fig.axes if a.images]


def test_volume_inversion_picture_panels_labels_and_values(tmp_path):
    res, inside, c = _sphere_result()
    fig = res.plot(tmp_path / "p.png", at="stiffest")
    panels = _panels(fig)
    assert len(panels) == 9                                         # 3 quantities x 3 orthogonal slices
    # "stiffest": the slices cut the middle of the stiff sphere, at its centre's element (8.5, 1.5, -0.5)
    titles = [a.get_title() for a in panels]
    assert titles[0].startswith(r"$\mu$, z = -0.5 mm") and titles[1] == r"$\mu$, y = 1.5 mm"
    assert titles[2] == r"$\mu$, x = 8.5 mm"
    assert titles[3].startswith(r"std of $\log\mu$") and titles[6].startswith(r"$\varepsilon_{xx}$")
    assert "grey: 4 of 1920 elements the data do not" in titles[3].replace("\n", " ")
    cbs = list(fig.volume_colorbars.values())                         # one per quantity, under its slices
    bars = [cb.ax.get_xlabel().replace("\n", " ") for cb in cbs]
    assert bars[0] == "shear modulus $\\mu$ / median (relative, one value per element)"
    assert bars[1] == ("uncertainty: std of $\\log\\mu$ (-, one value per element) low: more certain, high: less "
                       "certain")
    # the scale over the data (0.05 + 0.01 x depth: 1-99 % of it), not from 0, which no element is
    unorm = panels[3].images[0].norm
    assert 0.05 < unorm.vmin < 0.06 and 0.19 < unorm.vmax < 0.21, (unorm.vmin, unorm.vmax)
    assert bars[2] == "recovered axial strain $\\varepsilon_{xx}$ (%)"
    assert len(cbs) == 3 and all(cb.mappable in a.images for cb, a in zip(cbs, panels[::3]))
    # the axial-lateral modulus slice at z = -0.5 mm: each element's value over its whole box, mm extents
    al = panels[0].images[0]
    assert al.get_extent() == pytest.approx([-6.0, 6.0, 16.0, 0.0])  # lateral, then depth downwards
    img = np.ma.filled(al.get_array(), np.nan)
    assert img.shape == (80, 60)                                         # 5 samples per 1 mm element
    sel = np.abs(c[:, 2] + 0.5) < 1e-9
    want = np.full((16, 12), np.nan)
    want[np.floor(c[sel, 0]).astype(int), np.floor(c[sel, 1] + 6).astype(int)] = res.mu[sel]
    assert np.array_equal(img[2::5, 2::5], want)
    assert panels[0].get_aspect() == 1.0 and panels[0].get_xlabel() == "lateral y (mm)"
    assert panels[1].get_xlabel() == "elevational z (mm)" and panels[2].get_ylabel() == "elevational z (mm)"
    # uncertainty: the unconstrained elements are NaN (drawn grey), the others their value
    unc = np.ma.filled(panels[5].images[0].get_array(), np.nan)          # lateral-elevational at x = 8.5 mm
    assert np.all(np.isfinite(unc))                                      # no unconstrained element at x 8-9 mm
    assert panels[3].images[0].cmap.get_bad()[:3] == pytest.approx((0.75, 0.75, 0.75))
    # strain: -1 % everywhere (uniform compression)
    e = np.ma.filled(panels[6].images[0].get_array(), np.nan)
    assert np.allclose(e, -1.0)
    # modulus colour scale: 1-99 % of the elements (1 and 3 here), log, ticks at round values
    norm = panels[0].images[0].norm
    assert type(norm).__name__ == "LogNorm" and (norm.vmin, norm.vmax) == pytest.approx((0.8, 3.0))
    assert list(cbs[0].ax.get_xticks()) == [0.8, 1.0, 1.5, 2.0, 3.0]
    # no text over another panel: titles and colour bars clear of the other panels, tick labels apart
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for cb in cbs:
        tl = [t.get_window_extent(r) for t in cb.ax.get_xticklabels() if t.get_text()]
        assert len(tl) >= 2 and not any(x.overlaps(y) for i, x in enumerate(tl) for y in tl[i + 1:])
    boxes = [a.get_window_extent(r) for a in panels]
    for k, a in enumerate(panels):
        things = [a.title.get_window_extent(r)] + ([cbs[k // 3].ax.get_tightbbox(r)] if k % 3 == 0 else [])
        for t in things:
            assert t.x0 >= -1 and t.x1 <= fig.bbox.x1 + 1, titles[k]       # inside the figure
            for j, b in enumerate(boxes):
                if j != k:
                    assert not t.overlaps(b), (titles[k], titles[j])
    plt.close(fig)


def test_volume_inversion_picture_slice_choices_and_flag():
    res, inside, c = _sphere_result(success=False, with_uncertainty=False)
    res.constrained = np.ones(res.mu.size, bool)
    res.constrained[:5] = False
    fig = res.plot(at=(3.25, -4.05, 2.04))             # the nearest samples: 3.3, -4.1, 2.1 mm
    titles = [a.get_title() for a in _panels(fig)]
    assert len(titles) == 6                            # no uncertainty: modulus and strain rows
    assert titles[0].startswith(r"$\mu$, z = 2.1 mm") and "grey: 5 of 1920" in titles[0].replace("\n", " ")
    assert titles[1] == r"$\mu$, y = -4.1 mm" and titles[2] == r"$\mu$, x = 3.3 mm"
    banner = fig._suptitle
    assert banner.get_text().startswith("INVERSION FLAGGED: beta 0.0001 is the smallest")
    fig.canvas.draw()
    bb = banner.get_window_extent(fig.canvas.get_renderer())
    assert bb.x0 >= 0 and bb.x1 <= fig.bbox.x1                         # the banner fits the figure
    plt.close(fig)
    flat = InversionResult(mesh=res.mesh, mu=1.0 + 0.03 * np.sin(c[:, 0]), model="3d", lambda_bar=99.0,
                           beta=0.01, u_measured=res.u_measured, success=True, message="ok")
    fig = flat.plot()           # 3 % of variation does not fill the colour scale: it spans 0.8-1.25 at least
    norm = _panels(fig)[0].images[0].norm
    assert (norm.vmin, norm.vmax) == pytest.approx((0.8, 1.25))
    plt.close(fig)
    fig = res.plot()                                                    # default: the centre element
    assert _panels(fig)[0].get_title().startswith(r"$\mu$, z = 0.5 mm")
    assert _panels(fig)[2].get_title() == r"$\mu$, x = 8.5 mm"
    plt.close(fig)
    soft = InversionResult(mesh=res.mesh, mu=1.0 / res.mu, model="3d", lambda_bar=99.0, beta=0.01,
                           u_measured=res.u_measured, success=True, message="ok")
    fig = soft.plot(at="softest")
    assert [a.get_title() for a in _panels(fig)][:3] == [r"$\mu$, z = -0.5 mm", r"$\mu$, y = 1.5 mm",
                                                         r"$\mu$, x = 8.5 mm"]
    plt.close(fig)
    for at, words in (((40.0, 0.0, 0.0), "outside the inversion mesh"), ("middle", "stiffest"),
                      ((1.0, 2.0), "three")):
        with pytest.raises(InputError, match=words):
            res.plot(at=at)
    from skfem import MeshQuad1

    flat = InversionResult(mesh=MeshQuad1(), mu=np.ones(1), model="plane-stress", lambda_bar=2.0, beta=0.01)
    with pytest.raises(InputError, match="3D inversion only"):
        flat.plot(at="centre")


def test_cli_plot_and_measure_a_volume_inversion(tmp_path, capsys):
    res, inside, c = _sphere_result()
    mu = res.save(tmp_path / "mu.npz")
    rc, out, err = _run(["plot", mu, "-o", tmp_path / "a.png", "--slice", 8, 1, -1], capsys)
    assert rc == 0 and (tmp_path / "a.png").stat().st_size > 20_000
    rc, out, err = _run(["plot", mu, "-o", tmp_path / "b.png", "--slice", "stiffest"], capsys)
    assert rc == 0
    rc, out, err = _run(["plot", mu, "-o", tmp_path / "c.png", "--slice", 8, 1, 40], capsys)
    assert rc == 2 and "z = 40 mm lies outside the inversion mesh [-5, 5] mm" in err
    # measure: the sphere of the modulus map; elements wholly inside it hold 3, wholly outside 1
    rc, out, err = _run(["measure", mu, "--inclusion", 8.5, 1.5, -0.5, 3, "--json", tmp_path / "m.json"], capsys)
    assert rc == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["modulus_contrast"] == pytest.approx(3.0, rel=1e-12)
    assert m["SR"] == pytest.approx(1.0, rel=1e-9)                    # uniform compression: no strain contrast
    assert m["inclusion_mm"] == {"x": 8.5, "y": 1.5, "z": -0.5, "r": 3.0}
    assert "sphere, centre (8.5, 1.5, -0.5) mm" in out
    rc, out, err = _run(["measure", mu, "--inclusion", 8.5, 1.5, -0.5, 3, "--background", 0, 16, -6, 6, -5, 0], capsys)
    assert rc == 0 and "background: x 0-16, y -6-6, z -5-0 mm" in out
    for extra, words in ((["--inclusion", 8, 1, 3], "--inclusion takes 4 numbers (X Y Z R, mm)"),
                         (["--inclusion", 8, 1, -1, 3, "--background", 0, 16, -6, 6],
                          "--background takes 6 numbers"),
                         (["--inclusion", 30, 1, -1, 3], "lies outside the mesh (x 0.00 to 16.00 mm")):
        rc, out, err = _run(["measure", mu, *extra], capsys)
        assert rc == 2 and words in err and err.count("\n") == 1, err


def test_registered_volume_through_the_cli(tmp_path, capsys):
    """RF volumes -> femreg register -> femreg invert --images --png -> femreg plot --slice -> femreg measure."""
    from _volumes import volume_pair

    ref, mov, sp, _ = volume_pair(_layers(2.0, 4.0), shape=(400, 30, 24), seed=0)
    np.savez(tmp_path / "vols.npz", rf=np.stack([ref, mov]), spacing=sp)
    rc, out, err = _run(["register", tmp_path / "vols.npz", "-o", tmp_path / "reg.npz", "--element-size", 1],
                        capsys)
    assert rc == 0, err
    reg = femreg.load_result(tmp_path / "reg.npz")
    rc, out, err = _run(["invert", tmp_path / "reg.npz", "-o", tmp_path / "mu.npz", "--png", tmp_path / "mu.png",
                         "--slice", "centre", "--images", tmp_path / "vols.npz"], capsys)
    # 6 x 4 x 4 mm, 1 mm elements: the layers' ratio 2 comes out 0.94 (two-step) and stays below 1 after the one-step
    # inversion from the volumes; the strain says otherwise, so the result is written and flagged (exit 1)
    assert rc == 1 and "modulus contradicts strain" in err and "other side of 1" in err, err
    assert "one-step inversion from the images: image term" in out, out
    res = load_inversion(tmp_path / "mu.npz")
    assert res.one_step is not None and res.one_step["nit"] >= 1 and not res.success
    assert res.dim == 3 and np.array_equal(res.mesh.t, reg.mesh.t)      # on the registration's own mesh
    rc, out, err = _run(["plot", tmp_path / "mu.npz", "--slice", "stiffest"], capsys)
    assert rc == 1 and "drawn as such" in err and (tmp_path / "mu.png").is_file()     # the flagged result drawn
    rc, out, err = _run(["plot", tmp_path / "reg.npz"], capsys)       # the registration itself: its slices
    assert rc == (0 if reg.success else 1) and (tmp_path / "reg.png").is_file(), err
    rc, out, err = _run(["measure", tmp_path / "mu.npz", "--inclusion", 5.5, 2.9, 2.9, 1.6], capsys)
    assert rc == 1 and "modulus contrast" in out and "flagged inversion" in err, err
