"""A newcomer's high-frequency recording stored lines first: a 12.5 MHz linear array (40 MHz sampling, 0.1 mm
pitch) over superficial tissue (a bright skin line, the echo falling into the noise floor with depth), written as a
float32 .npy of shape (frames, lines, samples).

What went wrong before: the depth-only level (skin line, attenuation) is the same in every line and made the
lateral speckle read 62-114 RF periods wide, so the spacings typed the wrong way round (0.1 0.01925) passed the
swap check and were registered on a 208 mm deep, 2.5 mm wide image; the advice for the frames read without
--transpose named a spacing ten times too large ("centimetres", 1.24 MHz) because both orders gave a plausible
carrier; and a tracked frame accumulated through a flagged increment came back success=True."""
import numpy as np
import pytest

import femreg
import femreg.sequence
from femreg.cli import main
from femreg.orientation import diagnose
from _track_loop import ARGS, colorbar_labels, write_loop

AXIAL = 1540e3 / (2 * 40e6)        # c / (2 fs), mm: 0.01925
SPACING = (AXIAL, 0.1)


class _SkinCompression:
    """Uniform 0.5 % compression; scatterers above 1.5 mm twice as bright (the skin line)."""

    name, level = "skin", 0.005

    def __init__(self):
        from forward import fields

        self.f = fields.compression(self.level)

    def displacement(self, p):
        return self.f.displacement(p)

    def strain(self, p):
        return self.f.strain(p)

    def inside(self, p):
        return np.asarray(p)[:, 0] < 1.5


@pytest.fixture(scope="module")
def lines_first(tmp_path_factory):
    """A 20 mm deep pair, noise floor at 15 mm (no TGC), stored (frames, lines, samples) float32."""
    from forward.pairs import Probe, alpha_for_floor, attenuation_gain_db, make_pair

    pr = Probe(12.5, 40.0, 0.1, 0.35, 2.0, name="L12-5")
    pair = make_pair(_SkinCompression(), pr, size_mm=(20.0, 12.8), snr_db=30.0, seed=3, top_mm=0.0,
                     echo_gain_db=attenuation_gain_db(alpha_for_floor(15.0, 30.0, 12.5), 12.5))
    assert np.allclose(pair.spacing, SPACING)
    path = tmp_path_factory.mktemp("hf") / "scan.npy"
    np.save(path, np.stack([pair.ref.T, pair.mov.T]).astype(np.float32))
    return pair, path


def test_lateral_speckle_ignores_the_depth_level(lines_first):
    pair, _ = lines_first
    ok = diagnose(pair.ref, SPACING, whole_frame=True)
    swapped = diagnose(pair.ref, SPACING[::-1], whole_frame=True)
    # measured 6.5 and 0.24 periods (before: 114 and 4.2, the swap undetected)
    assert ok.problem == "" and 4.0 < ok.cell_periods < 10.0, (ok.problem, ok.cell_periods)
    assert swapped.problem == "swapped" and swapped.cell_periods < 0.5, (swapped.problem, swapped.cell_periods)


def _register_transposed(path, spacing, out, capsys):
    """``femreg register`` of the lines-first file with --transpose: (exit code, stderr)."""
    rc = main(["register", str(path), "--transpose", "--spacing", *spacing, "-o", str(out), "--no-progress"])
    return rc, capsys.readouterr().err


def test_swapped_spacing_is_refused_naming_the_right_one(lines_first, tmp_path, capsys):
    out = tmp_path / "p.npz"
    rc, err = _register_transposed(lines_first[1], ("0.1", "0.01925"), out, capsys)
    assert rc == 2, err
    assert "look swapped" in err and "--spacing 0.01925 0.1" in err, err
    assert not out.exists()


@pytest.mark.parametrize("given", [("0.01925", "0.1"), ("0.1", "0.01925")], ids=["kept", "exchanged"])
def test_transposed_advice_names_the_spacing_that_fits(lines_first, tmp_path, capsys, given):
    # either order of a spacing both of whose values give a plausible carrier: the lateral speckle says which is
    # axial (before: "units look like centimetres, --spacing 0.1925 1")
    _, path = lines_first
    rc = main(["register", str(path), "--spacing", *given, "-o", str(tmp_path / "p.npz"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "--transpose" in err and "--spacing 0.01925 0.1" in err, err
    assert "centimetres" not in err and "0.1925" not in err, err
    if given[0] == "0.01925":
        assert "keep --spacing 0.01925 0.1" in err, err


def test_right_spacing_registers(lines_first, tmp_path, capsys):
    out = tmp_path / "p.npz"
    rc, err = _register_transposed(lines_first[1], ("0.01925", "0.1"), out, capsys)
    assert rc == 0, err
    res = femreg.load_result(out)
    # the noise floor at 15 mm is found (the echo measured from the first sample's edge, 0.0 mm, not -0.0)
    assert "depth below 1" in res.excluded and " at 0.0-" in res.excluded and "-0.0" not in err, res.excluded
    exx = res.on_grid()["exx"]
    # true -0.5 %; measured -0.50 % median over the echo
    assert abs(np.nanmedian(exx) + 0.005) < 0.0005, np.nanmedian(exx)


# --- track: a frame accumulated through a flagged increment ------------------------------------------------------

@pytest.fixture(scope="module")
def track_file(tmp_path_factory):
    return write_loop(tmp_path_factory.mktemp("seq") / "frames.npy")


def test_frames_after_a_flagged_increment_are_failed(track_file, tmp_path, capsys, monkeypatch):
    real = femreg.sequence.register
    inits = []

    def failing_second(*a, **kw):
        inits.append(kw.get("initial") is None)
        r = real(*a, **kw)
        if len(inits) in (2, 3):    # frame 1 -> 2 fails its check, from the previous increment and afresh
            r.success, r.message = False, "FAILED: peak hopping (simulated)"
        return r

    monkeypatch.setattr(femreg.sequence, "register", failing_second)
    out = tmp_path / "run"
    rc = main(["track", str(track_file), "-o", str(out)] + ARGS)
    err = capsys.readouterr().err
    assert rc == 1, err
    assert "3 of 4 frame(s)" in err, err
    assert "--init blockmatch starts each afresh" in err, err
    res = {k: femreg.load_result(out / f"frame_{k:03d}.npz") for k in (1, 2, 3, 4)}
    assert res[1].success and not res[2].success
    assert "retried from a fresh start" in res[2].message and "flagged too" in res[2].message, res[2].message
    for k in (3, 4):
        assert not res[k].success
        assert res[k].message.startswith("FAILED: accumulated through frame 2"), res[k].message
    # frame 2 from frame 1's increment, then again afresh; afresh after the failed one only, frame 4 from frame 3's
    assert inits == [True, False, True, True, False], inits

    # a resumed run reads the same verdicts and starts frame 4 as the uninterrupted run did
    monkeypatch.undo()
    (out / "frame_004.npz").unlink()
    calls = []

    def spy(*a, **kw):
        calls.append(kw.get("initial") is None)
        return real(*a, **kw)

    monkeypatch.setattr(femreg.sequence, "register", spy)
    assert main(["track", str(track_file), "-o", str(out), "--resume"] + ARGS) == 1
    capsys.readouterr()
    assert calls == [False], calls
    assert femreg.load_result(out / "frame_004.npz").message.startswith("FAILED: accumulated through frame 2")


def test_failed_accumulated_frame_is_drawn_and_measured_as_failed(track_file, tmp_path, capsys, monkeypatch):
    real = femreg.sequence.register
    n = {"k": 0}

    def failing_second(*a, **kw):
        n["k"] += 1
        r = real(*a, **kw)
        if n["k"] in (2, 3):        # frame 2, from frame 1's increment and again afresh
            r.success, r.message = False, "FAILED: peak hopping (simulated)"
        return r

    monkeypatch.setattr(femreg.sequence, "register", failing_second)
    out = tmp_path / "run"
    assert main(["track", str(track_file), "-o", str(out)] + ARGS) == 1
    monkeypatch.undo()
    capsys.readouterr()
    last = out / "frame_004.npz"
    assert main(["measure", str(last), "--inclusion", "5", "5", "1"]) == 1
    cap = capsys.readouterr()
    assert "FLAGGED" in cap.out + cap.err, cap
    assert main(["invert", str(last), "-o", str(tmp_path / "mu.npz"), "--no-progress"]) == 2


# --- a JSON sidecar beside the .npy (fs Hz, c m/s, pitch m) --------------------------------------------------------

def _with_sidecar(lines_first, tmp_path, text):
    _, path = lines_first
    npy = tmp_path / "rec.npy"
    npy.write_bytes(path.read_bytes())
    (tmp_path / "rec.json").write_text(text)
    return npy


def test_info_names_the_spacing_a_sidecar_implies(lines_first, tmp_path, capsys):
    npy = _with_sidecar(lines_first, tmp_path, '{"fs": 40e6, "c": 1540, "pitch": 1e-4, "f0": 12.5e6, '
                                               '"probe": {"name": "L12-5", "frame_rate": 20}}')
    assert main(["info", str(npy), "--transpose"]) == 1
    out = capsys.readouterr().out
    assert "sidecar   rec.json" in out and "probe/frame_rate" in out, out
    assert "its fields suggest --spacing 0.01925 0.1" in out, out
    # the suggestion is never applied: register still needs --spacing, and says which
    rc = main(["register", str(npy), "--transpose", "-o", str(tmp_path / "p.npz"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "its fields suggest --spacing 0.01925 0.1" in err, err


def test_spacing_against_the_sidecar_is_noted(lines_first, tmp_path, capsys):
    npy = _with_sidecar(lines_first, tmp_path, '{"fs": 40e6, "c": 1540, "pitch": 1e-4}')
    rc = main(["register", str(npy), "--transpose", "--spacing", "0.01925", "0.125", "-o", str(tmp_path / "p.npz"),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "differs from what the file's fields imply (lateral 0.125 mm against 0.1" in err, err


def test_unreadable_sidecar_only_informs(lines_first, tmp_path, capsys):
    npy = _with_sidecar(lines_first, tmp_path, "{not json")
    assert main(["info", str(npy), "--transpose"]) == 1
    out = capsys.readouterr().out
    assert "sidecar   rec.json not read (JSONDecodeError" in out and "no spacing found" in out, out
    assert "its fields suggest" not in out, out


def test_measure_says_how_much_of_a_disk_off_the_edge_is_measured(lines_first, tmp_path, capsys):
    # a file without an origin puts the first line at y = 0: a disk meant at the centre line, typed at y = 1,
    # lies half outside the mesh
    _, path = lines_first
    out = tmp_path / "p.npz"
    assert main(["register", str(path), "--transpose", "--spacing", "0.01925", "0.1", "-o", str(out),
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["measure", str(out), "--inclusion", "8", "1", "2.5"]) == 0
    cap = capsys.readouterr()
    text = cap.out + cap.err
    assert "extends beyond the mesh (x " in text and "% of it, is measured" in text, text
    share = float(text.split("its part inside, ")[1].split(" %")[0])
    assert 35 <= share <= 65, share        # the mesh starts about 1 mm in: about half the disk


def test_raw_file_reads_its_sidecar_too(lines_first, tmp_path, capsys):
    _, path = lines_first
    raw = tmp_path / "rec.raw"
    np.load(path).tofile(raw)                     # (frames, lines, samples) float32, no header
    (tmp_path / "rec.json").write_text('{"fs": 40e6, "c": 1540, "pitch": 1e-4}')
    assert main(["info", str(raw), "--shape", "2", "1039", "128"]) == 1
    out = capsys.readouterr().out
    assert "sidecar   rec.json" in out and "its fields suggest --spacing 0.01925 0.1" in out, out


def test_flag_summary_names_accumulated_frames_once():
    from femreg.repair import summarise_flags

    own = "registration failed: peak hopping: 47% of the elements"
    taint = ("registration failed: accumulated through frame 2, whose increment was flagged (" + own + "); "
             "this frame's own increment: ")
    text = summarise_flags(["", own, taint + "converged", taint + "FAILED: peak hopping: 40%", ""])
    assert text == (f"frame 2: {own}; frame 4: registration failed: peak hopping: 40%; "
                    "frames 3, 4: accumulated through frame 2's flagged increment"), text
    assert summarise_flags(["", "low NCC after registration (0.4 < 0.5)"]) == \
        "frame 2: low NCC after registration (0.4 < 0.5)"


def test_volume_frames_after_a_flagged_increment_are_failed(monkeypatch):
    import femreg.volume
    from _volumes import affine_field, volume_pair

    shape, spacing = (300, 30, 24), (0.02, 0.2, 0.25)
    field, _ = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * spacing / 2)
    ref, mov, spacing, _ = volume_pair(field, shape=shape, f_mhz=7.0, seed=0)
    real, calls = femreg.volume.register_volume, []

    def failing_second(*a, **kw):
        r = real(*a, **kw)
        calls.append(r)
        if len(calls) in (2, 3):    # frame 2, from frame 1's increment and again afresh
            r.success, r.message = False, "FAILED: peak hopping (simulated)"
        return r

    monkeypatch.setattr(femreg.volume, "register_volume", failing_second)
    tr = femreg.track([ref, mov, ref, mov], spacing=spacing, element_size=2.0)
    assert len(tr) == 3 and [bool(f) for f in tr.flags] == [False, True, True], tr.flags
    assert len(calls) == 4 and tr.retried == [2], (len(calls), tr.retried)
    assert tr.accumulated[0].success and not tr.accumulated[2].success
    assert tr.accumulated[2].message.startswith("FAILED: accumulated through frame 2"), tr.accumulated[2].message
    assert tr.results[2].success        # the increment itself is kept as it came out


def test_modulus_colour_bar_within_a_decade_labels_the_lesion():
    """The lesion's modulus, 1.68 x the median over a 0.88-1.68 colour bar, had only 0.9 and 1 labelled."""
    labels = colorbar_labels([0.877, 1.682], 0.877, 1.682)
    assert labels == ["1", "1.25", "1.5"], labels
