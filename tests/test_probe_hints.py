"""Files from convex and phased arrays: header fields that state the probe geometry, the hint femreg info and the
readers' errors give from them, and the CLI's refusal to register such frames as a linear array's."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest

from femreg.io import read_frames
from femreg.io.checks import geometry_fields, geometry_hint, spacing_hint

h5py = pytest.importorskip("h5py")


def test_geometry_fields_units_and_names():
    g = geometry_fields({"probe/radius_mm": 50.0, "probe/angle_pitch_deg": 0.5})
    assert g["radius_mm"] == pytest.approx(50.0) and g["angle_pitch_deg"] == pytest.approx(0.5)
    # SI units told by magnitude: a radius of 0.06 (m) and 0.00873 (rad) between rays
    g = geometry_fields({"ROC": 0.06, "dtheta": np.deg2rad(0.5)})
    assert g["radius_mm"] == pytest.approx(60.0) and g["angle_pitch_deg"] == pytest.approx(0.5)
    assert geometry_fields({"angle_pitch": 60.0}) == {}        # a field of view, not the angle between rays
    # a radius without the angle between rays is still a convex array: the flag named, its value asked for
    assert geometry_fields({"radius_mm": 50.0}) == {"radius_mm": 50.0, "names": ("radius_mm = 50",)}
    assert "--geometry convex --radius 50 --angle-pitch DEG" in geometry_hint({"radius_mm": 50.0})
    assert "--geometry sector --angle-pitch 0.35" in geometry_hint({"line_angle_deg": 0.35})
    assert geometry_hint({"fs": 40e6, "pitch": 0.3}) == ""      # a linear array's header
    # with the rays' angle known, the lateral spacing is not asked for
    assert "--spacing 0.0385 auto" in spacing_hint({"fs": 20e6, "c": 1540.0, "angle_pitch_deg": 0.5})


@pytest.fixture(scope="module")
def convex_file(tmp_path_factory):
    from femreg import Convex
    from forward import fields as F
    from forward.beam import make_beam_pair

    p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                       depth_mm=12.0, n_rays=40, snr_db=30.0, seed=1)
    path = tmp_path_factory.mktemp("convex") / "acq.h5"
    with h5py.File(path, "w") as f:        # as a MATLAB h5write export: (frames, rays, samples), int16
        f["RData"] = np.round(np.stack([p.ref, p.mov]).transpose(0, 2, 1) * 1000).astype(np.int16)
        f.attrs["fs"] = 1540.0 / (2.0 * p.spacing[0] * 1e-3)
        f["probe/radius_mm"] = 40.0                       # scalar datasets, not attributes
        f["probe/angle_pitch_deg"] = 0.6
    return path, p


def test_scalar_datasets_are_fields(convex_file):
    path, p = convex_file
    fr = read_frames(path, spacing=(p.spacing[0], 0.4))
    fields = fr.metadata["fields"]
    assert fields["probe/radius_mm"] == 40.0 and fields["probe/angle_pitch_deg"] == pytest.approx(0.6)
    assert fr.frames.shape[1:] == p.ref.shape                   # transposed back to (samples, rays)


def test_cli_convex_file(convex_file, tmp_path, capsys):
    from femreg import load_result
    from femreg.cli import main

    def cli(argv):
        rc = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(argv, rc, out, err)

    path, p = convex_file
    dr = p.spacing[0]
    info = cli(["info", path])
    assert info.returncode == 1, info
    assert "--geometry convex --radius 40 --angle-pitch 0.6" in info.stdout
    assert f"--spacing {dr:.4g} auto" in info.stdout
    # registered as a linear array's lines: refused, naming the flags (exit 2, nothing computed)
    bad = cli(["register", path, "--spacing", dr, 0.3, "-o", tmp_path / "lin.npz"])
    assert bad.returncode == 2 and "--geometry convex --radius 40" in bad.stderr, bad.stderr
    assert not (tmp_path / "lin.npz").exists()
    bad = cli(["track", path, "--spacing", dr, 0.3, "-o", tmp_path / "run"])       # a cine loop alike
    assert bad.returncode == 2 and "--geometry convex --radius 40" in bad.stderr, bad.stderr
    bad = cli(["elastogram", path, "--spacing", dr, 0.3, "-o", tmp_path / "el"])   # it takes those flags too
    assert bad.returncode == 2 and "--geometry convex --radius 40" in bad.stderr, bad.stderr
    # the geometry given: no lateral spacing needed; a given one is said to be unused
    ok = cli(["register", path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.6,
              "--spacing", dr, "auto", "-o", tmp_path / "convex.npz"])
    assert ok.returncode == 0, ok.stderr
    res = load_result(tmp_path / "convex.npz")
    assert type(res).__name__ == "BeamResult"
    g = res.on_grid()
    e = np.nanmedian(g["exx"])
    assert -0.0125 < e < -0.0075, e                             # 1 % compression, within 25 %
    noted = cli(["register", path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.6,
                 "--spacing", dr, 0.3, "--maxiter", 1, "-o", tmp_path / "c2.npz"])
    assert "the lateral spacing 0.3 is not used" in noted.stderr and noted.returncode in (0, 1)
    # --geometry linear given explicitly: the user's word wins over the header
    lin = cli(["register", path, "--geometry", "linear", "--spacing", dr, 0.4, "--maxiter", 1,
               "-o", tmp_path / "lin2.npz"])
    assert lin.returncode in (0, 1) and "suggest a convex array" not in lin.stderr, lin.stderr


def test_convex_result_loads_with_its_geometry(convex_file, tmp_path):
    """A saved convex result reads back as a BeamResult: its samples at their physical positions, not on a
    Cartesian grid of (range step, lateral spacing)."""
    import femreg

    path, p = convex_file
    res = femreg.register(p.ref, p.mov, spacing=p.spacing[0], origin=p.origin, geometry=p.geometry, maxiter=2)
    res.save(tmp_path / "c.npz")
    back = femreg.load_result(tmp_path / "c.npz")
    assert isinstance(back, femreg.geometry.BeamResult)
    assert back.geometry.radius_mm == pytest.approx(40.0)
    np.testing.assert_allclose(back.pixel_points(), res.pixel_points())
    a, b = res.on_grid("element"), back.on_grid("element")      # recomputed from the mesh, not the stored grid
    np.testing.assert_allclose(b["exx"], a["exx"], equal_nan=True, atol=1e-12)


def test_axis_fields_find_evenly_spaced_vectors():
    from femreg.io.checks import axis_fields

    theta = (np.arange(80) - 39.5) * np.deg2rad(0.5)
    ax = axis_fields([("theta", theta[None, :]), ("tgc", np.linspace(0, 1, 50) ** 2), ("fs", np.array(2e7)),
                      ("depth", np.arange(3.0)), ("two", np.array([1.0, 2.0]))])
    assert set(ax) == {"theta", "depth"}                        # a TGC curve is not an axis, nor two values
    assert ax["theta"]["n"] == 80 and ax["theta"]["step"] == pytest.approx(np.deg2rad(0.5))
    # a vector of the rays' angles with one value per line gives the pitch; a plane-wave sequence's 7 steering
    # angles are not one per line
    g = geometry_fields({"ROC": 0.0412}, ax, 80)
    assert g["radius_mm"] == pytest.approx(41.2) and g["angle_pitch_deg"] == pytest.approx(0.5)
    assert "angle_pitch_deg" not in geometry_fields({"ROC": 0.0412}, ax)   # the number of lines unknown: unused
    steer = axis_fields([("angles", np.deg2rad(np.linspace(-9, 9, 7)))])
    assert geometry_fields({}, steer, 128) == {} and geometry_fields({}, ax, 96) == {}
    assert geometry_fields({}, axis_fields([("scan/theta_deg", np.linspace(-20, 20, 81))]), 81)[
        "angle_pitch_deg"] == pytest.approx(0.5)


@pytest.fixture(scope="module")
def mat73_theta_file(tmp_path_factory):
    """A MATLAB -v7.3 file as a user saves beamformed convex RF: rf(samples, rays, frames) int16, fs in Hz, the
    radius in metres and a vector of the rays' angles in radians (no angle-pitch scalar)."""
    from femreg import Convex
    from forward import fields as F
    from forward.beam import make_beam_pair

    p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                       depth_mm=12.0, n_rays=40, snr_db=30.0, seed=1)
    path = tmp_path_factory.mktemp("mat73") / "scan.mat"
    rf = np.round(np.stack([p.ref, p.mov]) * 1000).astype(np.int16)         # (frames, samples, rays)
    with h5py.File(path, "w", userblock_size=512) as f:   # MATLAB's HDF5 holds the reversed index order
        f["rf"] = np.ascontiguousarray(rf.transpose(0, 2, 1))
        f["fs"] = np.array([[1540.0 / (2.0 * p.spacing[0] * 1e-3)]])
        f["ROC"] = np.array([[0.040]])
        f["theta"] = ((np.arange(40) - 19.5) * np.deg2rad(0.6))[:, None]
        f["t0"] = np.array([[2.0 * p.origin[0] * 1e-3 / 1540.0]])        # receive start, s: the first range
    with open(path, "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, HDF5 schema 1.00 .".ljust(116) + b"\x00" * 8 + b"\x00\x02IM")
    return path, p


def test_ray_angle_vector_states_the_probe(mat73_theta_file, tmp_path, capsys):
    from femreg.cli import main

    path, p = mat73_theta_file
    dr = f"{p.spacing[0]:.4g}"

    def cli(*argv):
        rc = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return rc, out, err

    rc, out, _ = cli("info", path)
    assert rc == 1 and "--geometry convex --radius 40 --angle-pitch 0.6" in out, out
    assert f"--spacing {dr} auto" in out and "40 values from" in out, out
    # read as a linear array's lines: refused, naming the flags (before, registered silently)
    rc, _, err = cli("register", path, "--spacing", dr, 0.3, "-o", tmp_path / "lin.npz")
    assert rc == 2 and "--geometry convex --radius 40 --angle-pitch 0.6" in err, err
    # the geometry given but no range step: the message asks for DX alone (the rays are --angle-pitch apart)
    for cmd in ("register", "track"):
        rc, _, err = cli(cmd, path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.6,
                         "-o", tmp_path / f"nodx_{cmd}")
        assert rc == 2 and "pass --spacing DX auto" in err and f"DX = {dr}" in err and "DY" not in err, err
    # a probe contradicting the file's own header: refused (an angle pitch off by 10x passes the speckle check)
    rc, _, err = cli("register", path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.06,
                     "--spacing", dr, "auto", "-o", tmp_path / "c.npz")
    assert rc == 2 and "--angle-pitch 0.06 deg against 0.6 deg" in err, err
    rc, _, err = cli("track", path, "--geometry", "convex", "--radius", 45, "--angle-pitch", 0.6,
                     "--spacing", dr, "auto", "-o", tmp_path / "run")
    assert rc == 2 and "--radius 45 mm against 40 mm" in err, err
    assert not (tmp_path / "c.npz").exists() and not (tmp_path / "run").exists()
    # the header's start time: named by info; register applies it as the first range of convex frames (the
    # fan's geometry needs it), saying so; a given --origin wins
    r0 = f"{p.origin[0]:.4g}"
    rc, out, _ = cli("info", path)
    assert f"pass --origin {r0} 0" in out and "applied as the first range" in out, out
    rc, _, err = cli("register", path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.6,
                     "--spacing", dr, "auto", "--maxiter", 1, "-o", tmp_path / "c0.npz")
    assert rc in (0, 1) and f"taken at range {r0} mm" in err, err
    rc, _, err = cli("register", path, "--geometry", "convex", "--radius", 40, "--angle-pitch", 0.6,
                     "--spacing", dr, "auto", "--origin", 0, 0, "--maxiter", 1, "-o", tmp_path / "c1.npz")
    assert rc in (0, 1) and "start depth" not in err, err
    with np.load(tmp_path / "c0.npz") as a, np.load(tmp_path / "c1.npz") as b:
        # the mesh's nodes lie on the fan of the first range used: the nearest to the apex at R + r0
        ra, rb = (np.hypot(z["mesh_points"][0] + 40.0, z["mesh_points"][1]).min() - 40.0 for z in (a, b))
    assert ra - rb == pytest.approx(p.origin[0], abs=0.05), (ra, rb)


def test_origin_overrides_the_file(mat73_theta_file):
    from femreg.errors import InputError

    path, p = mat73_theta_file
    fr = read_frames(path, spacing=(p.spacing[0], 0.6), origin=(2.5, 0.0))
    assert fr.origin == (2.5, 0.0) and fr.metadata["origin_given"]
    assert read_frames(path, spacing=(p.spacing[0], 0.6)).origin == (0.0, 0.0)
    with pytest.raises(InputError, match="origin must be two finite numbers"):
        read_frames(path, spacing=(p.spacing[0], 0.6), origin=(1.0, float("nan")))
    from femreg.io.checks import origin_hint

    assert origin_hint({"t0": 6.4935e-7})[0] == pytest.approx(0.5, rel=1e-3)
    assert origin_hint({"start_depth_mm": 12.0})[0] == 12.0 and origin_hint({"r0": 0.02})[0] == pytest.approx(20.0)
    assert origin_hint({"t0_us": 13.0})[0] == pytest.approx(10.01) and origin_hint({"fs": 4e7}) == (None, "")


def test_angle_pitch_in_radians_is_named(mat73_theta_file):
    """An angle pitch given in radians puts the rays 57x too close: the refusal names the degrees to pass, not a
    swap of the axial and lateral spacings (which a convex frame does not have)."""
    import femreg
    from femreg.orientation import OrientationError

    _, p = mat73_theta_file
    with pytest.raises(OrientationError, match=r"looks given in radians.*--angle-pitch 0\.6"):
        femreg.register(p.ref, p.mov, spacing=p.spacing[0], origin=p.origin,
                        geometry=femreg.Convex(radius_mm=40.0, angle_pitch_deg=np.deg2rad(0.6)))


def test_origin_on_a_volume_is_refused(tmp_path, capsys):
    from femreg.cli import main

    rng = np.random.default_rng(0)
    path = tmp_path / "vol.npz"
    np.savez(path, rf=rng.standard_normal((2, 40, 8, 6)), spacing=np.array([0.02, 0.2, 0.4]))
    for cmd in (["register", path, "-o", tmp_path / "r.npz"], ["track", path, "-o", tmp_path / "run"]):
        assert main([str(a) for a in cmd] + ["--origin", "1", "0"]) == 2
        assert "a volume's origin comes from its file" in capsys.readouterr().err
