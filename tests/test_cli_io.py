"""`femreg info` and `femreg plot`: outputs, exit codes and one-line messages on bad input."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from femreg.cli import main
from femreg.io import save_frames, save_result
from test_io import INVIVO, _affine_u, _quad_mesh, _result


def _err_line(capsys):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


@pytest.mark.parametrize("cmd", ["info", "plot"])
def test_help(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--variable", "--shape", "--dtype", "--spacing", "--byte-order", "--frames"):
        assert flag in out, (cmd, flag)


def test_info_text_and_json(tmp_path, capsys):
    rf = np.random.default_rng(0).standard_normal((4, 30, 8)).astype(np.float32)
    save_frames(tmp_path / "a.mhd", rf, (0.05, 0.3), byte_order="big")
    assert main(["info", str(tmp_path / "a.mhd")]) == 0
    out = capsys.readouterr().out
    assert "metaimage" in out and "30 axial x 8 lateral" in out and "0.05 mm axial" in out, out
    assert "ElementType" in out and "big" in out
    assert main(["info", str(tmp_path / "a.mhd"), "--json", "--frames", "1:3", "--spacing", "auto", "0.25"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 2 and info["shape"] == [30, 8] and info["spacing_mm"] == [0.05, 0.25]
    assert info["min"] == pytest.approx(float(rf[1:3].min()))


def test_info_raw_with_reader_flags(tmp_path, capsys):
    a = (np.arange(3 * 10 * 4) - 50).astype(">i2")
    a.tofile(tmp_path / "x.bin")
    argv = ["info", str(tmp_path / "x.bin"), "--shape", "10", "4", "--dtype", "int16", "--byte-order", "big",
            "--spacing", "0.1", "0.2", "--json"]
    assert main(argv) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 3 and info["min"] == -50 and info["max"] == 69, info


@pytest.mark.parametrize("setup,argv,needle", [
    (None, ["missing.npz"], "no such file"),
    ("raw", ["x.raw"], "shape"),
    ("raw", ["x.raw", "--shape", "7", "3"], "size mismatch"),
    ("raw", ["x.raw", "--shape", "1", "2", "3", "4"], "--shape"),
    ("raw", ["x.raw", "--shape", "10", "4", "--dtype", "complex", "--spacing", "1", "1"], "dtype"),
    ("rf", ["t.rf", "--spacing", "auto", "0.3"], "truncated"),
    ("npz", ["k.npz", "--variable", "nope"], "missing variable 'nope'"),
])
def test_info_bad_input_exit_2_one_line(tmp_path, capsys, monkeypatch, setup, argv, needle):
    monkeypatch.chdir(tmp_path)
    if setup == "raw":
        np.zeros((10, 4), np.float32).tofile("x.raw")
    elif setup == "rf":
        save_frames("t.rf", np.zeros((2, 8, 4)), (0.02, 0.3))
        Path("t.rf").write_bytes(Path("t.rf").read_bytes()[:-5])
    elif setup == "npz":
        save_frames("k.npz", np.zeros((8, 4)), (0.02, 0.3))
    assert main(["info"] + argv) == 2
    err = _err_line(capsys)
    assert err.startswith("femreg info: error:") and needle in err, err


def test_info_describes_a_file_without_spacing_and_says_what_it_needs(tmp_path, capsys):
    rf = (np.random.default_rng(1).standard_normal((2, 40, 6)) * 1000).astype(np.int16)
    np.save(tmp_path / "a.npy", rf)
    assert main(["info", str(tmp_path / "a.npy")]) == 1           # described; registering it needs a spacing
    out = capsys.readouterr().out
    assert "int16 as stored" in out and "40 axial x 6 lateral" in out and "--spacing DX DY" in out, out
    rf.tofile(tmp_path / "a.raw")
    assert main(["info", str(tmp_path / "a.raw"), "--shape", "40", "6", "--dtype", "int16", "--json"]) == 1
    info = json.loads(capsys.readouterr().out)
    assert info["dtype"] == "int16" and info["frames"] == 2 and info["spacing_mm"] is None
    assert any("--spacing" in n for n in info["needs"])
    assert main(["info", str(tmp_path / "a.npy"), "--spacing", "0.02", "0.2", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["spacing_mm"] == [0.02, 0.2] and info["dtype"] == "int16"
    save_frames(tmp_path / "a.rf", rf, (0.02, 0.2))                  # Ultrasonix: int16 samples, no lateral pitch
    main(["info", str(tmp_path / "a.rf"), "--json"])
    info = json.loads(capsys.readouterr().out)
    assert info["dtype"] == "int16" and any("--spacing" in n for n in info["needs"]), info
    # the header's sampling frequency gives the axial half: named in the text, not "none in the file"
    assert main(["info", str(tmp_path / "a.rf")]) == 1
    out = capsys.readouterr().out
    assert "suggest --spacing 0.02 DY" in out and "none in the file" not in out, out


def test_argparse_errors_exit_2(capsys):
    for argv in (["info"], ["info", "x", "--frames", "a:b"], ["info", "x", "--spacing", "0", "1"],
                 ["plot", "r.npz", "--field", "nope"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2, argv
        assert "error" in capsys.readouterr().err


def test_info_invivo(capsys):
    seq = INVIVO / "seq304"
    if not seq.is_dir():
        pytest.skip(f"in vivo data not found at {INVIVO}")
    assert main(["info", str(seq), "--shape", "2000", "128", "--spacing", "0.02", "0.2", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 6 and info["shape"] == [2000, 128] and info["spacing_mm"] == [0.02, 0.2]


def test_info_raw_read_with_the_sizes_exchanged_names_the_shape(tmp_path, capsys):
    """A raw RF frame read as lines x samples is scrambled (not transposed), so the orientation check sees no
    carrier at all; info says which --shape reads it, and stays quiet on the right shape and on an envelope."""
    from scipy.signal import hilbert

    from femreg.synthetic import speckle_pair

    rf, _ = speckle_pair(lambda q: 0.0 * q, shape=(600, 80), spacing=(0.02, 0.1), seed=4)
    rf.astype("<f4").tofile(tmp_path / "rf.raw")
    np.abs(hilbert(rf, axis=0)).astype("<f4").tofile(tmp_path / "env.raw")
    for spacing in (["--spacing", "0.1", "0.02"], []):
        assert main(["info", str(tmp_path / "rf.raw"), "--shape", "80", "600", *spacing]) == 1
        assert "the --shape looks exchanged, pass --shape 600 80" in capsys.readouterr().out, spacing
    assert main(["info", str(tmp_path / "rf.raw"), "--shape", "600", "80", "--spacing", "0.02", "0.1"]) == 0
    assert "exchanged" not in capsys.readouterr().out
    assert main(["info", str(tmp_path / "env.raw"), "--shape", "600", "80", "--spacing", "0.02", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "no RF carrier along axis 0" in out and "exchanged" not in out


def test_register_and_track_refuse_raw_read_with_the_sizes_exchanged(tmp_path, capsys):
    """register, track and elastogram refuse (exit 2, nothing written) the raw frames that info says were read
    with their sizes exchanged: as read they carry no carrier and would register as envelope data (a scrambled
    pair ran to NCC 0.21 with a result written, a scrambled folder tracked 4 of 5 frames unflagged)."""
    from femreg.synthetic import speckle_pair

    rf0, rf1 = speckle_pair(lambda q: np.column_stack([-0.01 * q[:, 0], 0.0 * q[:, 1]]), shape=(600, 80),
                            spacing=(0.02, 0.1), seed=4)
    rec = tmp_path / "rec"
    rec.mkdir()
    for k, rf in enumerate((rf0, rf1, rf0)):
        rf.astype("<f4").tofile(rec / f"frame{k + 1}.raw")
    wrong = ["--shape", "80", "600", "--spacing", "0.1", "0.02"]
    cases = (["register", str(rec / "frame1.raw"), str(rec / "frame2.raw"), "-o", str(tmp_path / "p.npz")],
             ["track", str(rec), "-o", str(tmp_path / "run")],
             ["elastogram", str(rec), "-o", str(tmp_path / "loop")])
    for argv in cases:
        assert main([*argv, *wrong]) == 2, argv
        assert "the --shape looks exchanged, pass --shape 600 80" in capsys.readouterr().err, argv
    assert not (tmp_path / "p.npz").exists() and not (tmp_path / "run").exists()
    # the override reads them as given (the user knows better)
    assert main([*cases[0], *wrong, "--no-orientation-check"]) in (0, 1)
    capsys.readouterr()
    assert main([*cases[0], "--shape", "600", "80", "--spacing", "0.02", "0.1"]) == 0


def test_plot_writes_png_vtu_xdmf_render(tmp_path, capsys):
    p, t = _quad_mesh(6, 4)
    res = _result(p, t, _affine_u(p, np.eye(2) * 0.01), shape=(40, 30))
    save_result(tmp_path / "r.npz", res)
    ref = np.random.default_rng(2).standard_normal((2, 40, 30))
    save_frames(tmp_path / "ref.npy", ref)
    argv = ["plot", str(tmp_path / "r.npz"), "-o", str(tmp_path / "o.png"), "--vtu", str(tmp_path / "o.vtu"),
            "--xdmf", str(tmp_path / "o.xdmf"), "--render", str(tmp_path / "m.png"), "--field", "ux",
            "--reference", str(tmp_path / "ref.npy"), "--spacing", "0.05", "0.075", "--frame", "1", "--overlay",
            "--dpi", "40"]
    assert main(argv) == 0, capsys.readouterr().err
    for name in ("o.png", "o.vtu", "o.xdmf", "o.h5", "m.png"):
        assert (tmp_path / name).stat().st_size > 100, name
    assert main(["plot", str(tmp_path / "r.npz"), "--dpi", "30"]) == 0  # default output next to the result
    assert (tmp_path / "r.png").stat().st_size > 1000


def test_plot_bad_input(tmp_path, capsys):
    p, t = _quad_mesh()
    res = _result(p, t, _affine_u(p, np.eye(2) * 0.01))
    save_result(tmp_path / "r.npz", res)
    bad = dict(res)
    del bad["mesh_cells"]
    np.savez(tmp_path / "bad.npz", **bad)
    cases = [(["bad.npz"], "missing key"), (["nothere.npz"], "no such result"),
             (["r.npz", "-o", "x.jpg"], ".png"), (["r.npz", "--overlay"], "--reference"),
             (["r.npz", "--reference", "nothere.npy"], "no such file"),
             (["r.npz", "--vtu", "x.vtu", "--xdmf", "x.obj"], "--xdmf must name a .xdmf"),
             (["run"], "a folder, not a result file: name one of its 1 result files, e.g. ")]
    (tmp_path / "run").mkdir()
    save_result(tmp_path / "run" / "frame_001.npz", res)              # a track folder
    for argv, needle in cases:
        argv = [str(tmp_path / a) if a.endswith((".npz", ".npy", ".vtu", ".obj", "run")) else a for a in argv]
        assert main(["plot"] + argv) == 2, argv
        err = _err_line(capsys)
        assert err.startswith("femreg plot: error:") and needle in err, (argv, err)
    assert not (tmp_path / "x.vtu").exists()  # bad arguments are caught before anything is written


def test_console_entry_point_exit_code(tmp_path):
    (tmp_path / "z.npz").write_bytes(b"PK\x03\x04 this is not a zip")
    proc = subprocess.run([sys.executable, "-m", "femreg.cli", "info", str(tmp_path / "z.npz")],
                          capture_output=True, text=True, cwd=Path(__file__).parents[1])
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "z.npz" in proc.stderr


def test_python_m_femreg_is_the_femreg_command():
    proc = subprocess.run([sys.executable, "-m", "femreg", "--version"], capture_output=True, text=True,
                          cwd=Path(__file__).parents[1])
    import femreg

    assert proc.returncode == 0 and proc.stdout.strip() == f"femreg {femreg.__version__}", proc.stderr


def test_engine_result_plots_and_exports(tmp_path, capsys):
    """An engine result saved by ``res.save`` goes through `femreg plot` and VTU export; the VTU cell strains
    (element centres, femreg.io) agree with the engine's element strain ``res.strain(..., "element")`` there and
    the VTU point strains with its recovered nodal strains."""
    import meshio

    import femreg
    from femreg.synthetic import speckle_pair

    spacing = (0.02, 0.1)
    shape = (300, 60)
    ref, mov = speckle_pair(lambda p: np.c_[0.005 * p[:, 0], -0.002 * p[:, 1]], shape=shape, spacing=spacing,
                            seed=1)
    res = femreg.register(ref, mov, spacing=spacing, regularizer="strain", element_size=(1.0, 1.0),
                          initial="zero", maxiter=5)
    res.save(tmp_path / "r.npz")
    save_frames(tmp_path / "ref.npz", ref, spacing)
    argv = ["plot", str(tmp_path / "r.npz"), "--reference", str(tmp_path / "ref.npz"), "-o", str(tmp_path / "o.png"),
            "--vtu", str(tmp_path / "o.vtu"), "--dpi", "40"]
    assert main(argv) == 0, capsys.readouterr().err
    assert (tmp_path / "o.png").stat().st_size > 1000
    m = meshio.read(tmp_path / "o.vtu")
    centres = m.points[m.cells[0].data].mean(axis=1)[:, :2]  # exact centres for the engine's rectangles
    expect = res.strain(centres, "element")
    for k, name in enumerate(("exx", "eyy", "exy")):
        err = np.abs(m.cell_data[name][0] - expect[:, k]).max()
        assert err < 1e-10, (name, err)
        err = np.abs(m.point_data[name] - res.nodal_strain[:, k]).max()
        assert err < 1e-10, (name, err)
    np.testing.assert_allclose(m.point_data["displacement"][:, :2], res.u.reshape(-1, 2), atol=0)


def test_engine_displacement_at_nodes_equals_nodal_u():
    import femreg
    from femreg.synthetic import speckle_pair

    ref, mov = speckle_pair(lambda p: np.c_[0.005 * p[:, 0], -0.002 * p[:, 1]], shape=(300, 60),
                            spacing=(0.02, 0.1), seed=1)
    res = femreg.register(ref, mov, spacing=(0.02, 0.1), regularizer="strain", element_size=(1.0, 1.0), initial="zero", maxiter=2)
    nodes = res.mesh.p.T
    err = np.abs(res.displacement(nodes) - res.u.reshape(-1, 2)).max()
    assert err < 1e-12, f"max |u(node) - u_node| = {err:.3g} mm"


def test_swapped_spacing_from_a_metaimage_header_says_where_it_came_from(tmp_path, capsys):
    """A MetaImage header's ElementSpacing lists the lateral spacing first; written in (axial, lateral) order it
    is refused (exit 2), and the message says the spacing came from the file and that --spacing overrides it."""
    from forward import fields as F
    from forward.pairs import PROBES, make_pair

    p = make_pair(F.compression(0.01), PROBES["L7"], (15, 10), 20, seed=3)
    dx, dy = (float(v) for v in p.spacing)
    save_frames(tmp_path / "s.mhd", np.stack([p.ref, p.mov]), (dy, dx))         # the mistake: lateral first
    out = tmp_path / "pair.npz"
    assert main(["register", str(tmp_path / "s.mhd"), "-o", str(out)]) == 2
    err = _err_line(capsys)
    assert "look swapped" in err and "read from the file" in err and "ElementSpacing" in err, err
    assert not out.exists()
    # the override it names works (exit 0), and a spacing given on the command line gets no header note
    assert main(["register", str(tmp_path / "s.mhd"), "-o", str(out), "--spacing", f"{dx:g}", f"{dy:g}"]) == 0
    capsys.readouterr()
    assert main(["register", str(tmp_path / "s.mhd"), "-o", str(out), "--spacing", f"{dy:g}", f"{dx:g}"]) == 2
    assert "read from the file" not in _err_line(capsys)


def test_output_closed_early_is_not_an_error(tmp_path, monkeypatch, capsys):
    """`femreg info FILE | head`: the pipe closes early; femreg stops quietly with 141 (128 + SIGPIPE), no error
    line on stderr."""
    rf = np.random.default_rng(0).standard_normal((2, 30, 8)).astype(np.float32)
    save_frames(tmp_path / "a.npz", rf, (0.05, 0.3))
    import femreg.cli.info_cmd as info_cmd

    def closed(*args, **kwargs):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(info_cmd, "print", closed, raising=False)
    assert main(["info", str(tmp_path / "a.npz")]) == 141
    assert capsys.readouterr().err == ""
