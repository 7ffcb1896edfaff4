"""femreg.elastogram / `femreg elastogram` on simulated freehand loops (forward.freehand): the chosen pairs lie in
the strain band and register to the true strain, the persistent elastogram is at least as accurate as the best
single pair, the files and exit codes of the command, --resume after an interruption."""
import csv

import numpy as np
import pytest

from femreg.cli import main
from femreg.elastogram import DEFAULT_BAND, PAIR_COLUMNS, elastogram, screen_pairs
from femreg.errors import InputError
from forward.freehand import FreehandMotion, simulate_freehand

from _torn import tear_atomic_write

# 40 frames at 30 Hz: press/release at 1.5 Hz to 2 %, a pause, the probe sliding 1 mm/s laterally and 1 mm/s out of
# plane, and a x2.5 gain step at frame 25.
MOTION = FreehandMotion(n_frames=40, press_hz=1.5, amplitude=0.02, pauses=((0.5, 0.7),), slide_mm_s=1.0,
                        elevation_mm_s=1.0, gain_steps=((25, 2.5),))


@pytest.fixture(scope="module")
def loop():
    return simulate_freehand(MOTION, seed=6)


@pytest.fixture(scope="module")
def run(loop, tmp_path_factory):
    out = tmp_path_factory.mktemp("elastogram")
    res = elastogram(loop.frames, spacing=loop.spacing, origin=loop.origin, output_dir=out)
    return res, out


def _normalised_error(loop, est, i, margin=0.1):
    """RMS of (estimated - true) normalised axial strain, percent, over the covered pixels less 10 % of the depth
    at the top and bottom."""
    pat = loop.strain_pattern(i, loop.pixel_points()).reshape(est.shape)
    ok = np.isfinite(est)
    m = int(margin * est.shape[0])
    ok[:m] = ok[-m:] = False
    return 100 * float(np.sqrt(np.mean((est[ok] / np.mean(est[ok]) - pat[ok] / np.mean(pat[ok])) ** 2)))


def _pair_files(out):
    got = {}
    for f in sorted((out / "pairs").glob("pair_*.npz")):
        with np.load(f) as z:
            got[(int(z["ref"]), int(z["mov"]))] = {k: z[k] for k in z.files}
    return got


def test_selected_pairs_lie_in_the_band_and_match_the_truth(loop, run):
    res, out = run
    lo, hi = DEFAULT_BAND
    chosen = [r for r in res.pairs if r["registered"]]
    # 40 frames at 1.5 Hz: 2.7 press/release strokes, each of about 2 % -> 4-8 pairs of ~1 %
    assert len(chosen) >= 4 and res.n_usable == len(chosen), res.pairs
    files = _pair_files(out)
    assert set(files) == {(r["ref"], r["mov"]) for r in chosen}
    P = loop.pixel_points()
    for (i, j), z in files.items():
        ms = float(z["mean_strain"])
        assert lo <= abs(ms) <= hi, (i, j, ms)
        exx = z["exx"].astype(float)
        true = loop.true_strain(i, j, P)[:, 0].reshape(exx.shape)[np.isfinite(exx)].mean()
        # measured: within 1.7 % of the true mean strain (seeds 5-7); bound 3 %
        assert abs(ms - true) <= 0.03 * abs(true), (i, j, ms, true)
    # not selected: consecutive pairs in the band would have been taken; the chosen intervals do not overlap
    steps = np.zeros(len(loop.frames), int)
    for r in chosen:
        steps[r["ref"]:r["mov"]] += 1
    assert steps.max() == 1


def test_elastogram_at_least_as_accurate_as_the_best_single_pair(loop, run):
    res, out = run
    single = {k: _normalised_error(loop, z["exx"].astype(float), k[0]) for k, z in _pair_files(out).items()}
    best_single = min(single.values())
    err = _normalised_error(loop, res.exx, res.ref_frame)
    # measured (seed 6): 4.38 % against the best pair's 4.88 % (seeds 5 / 7: 3.86 vs 3.89, 4.14 vs 4.53)
    assert err <= best_single, (err, single)
    assert res.cine.shape[0] == res.n_usable and res.cine.shape[2] == loop.frames.shape[2]
    assert res.exx.shape == loop.frames.shape[1:]
    assert abs(np.nanmean(res.exx) - 1.0) < 0.05          # normalised: mean 1, compression and release alike


def test_freehand_schedule_pauses_and_gain_steps(loop):
    t = loop.time
    held = (t >= 0.5) & (t < 0.7)
    assert held.sum() >= 5 and np.ptp(loop.compression[held]) == 0          # the hand holds still
    assert loop.compression.max() <= 0.02 + 1e-12 and loop.compression.min() >= 0
    assert np.all(loop.gain[:25] == 1.0) and np.all(loop.gain[25:] == 2.5)
    rms = np.sqrt(np.mean(loop.frames ** 2, axis=(1, 2)))
    assert 2.0 < rms[26] / rms[24] < 3.0
    # out-of-plane drift decorrelates: frame 0 against frame 39 (1.3 mm apart in elevation) less alike than 0 vs 1
    c = [np.corrcoef(loop.frames[0].ravel(), loop.frames[k].ravel())[0, 1] for k in (1, 39)]
    assert c[1] < c[0]


def test_screening_chooses_non_overlapping_pairs_in_band():
    # consecutive strains of a steady 0.3 %/frame compression: pairs of 3 frames (0.9 %), none overlapping
    e = np.full(12, -0.003)
    rows = screen_pairs(e, np.zeros(12), np.full(12, 0.95), band=(0.005, 0.02))
    sel = [(r["ref"], r["mov"]) for r in rows if r["selected"]]
    assert len(sel) == 4 and all(j - i == 3 for i, j in sel), sel
    # decorrelated (out-of-plane) pairs are not chosen
    rows = screen_pairs(e, np.zeros(12), np.full(12, 0.3), band=(0.005, 0.02), min_ncc=0.6)
    assert not any(r["selected"] for r in rows)


def test_cli_files_exit_codes_and_resume(loop, tmp_path, capsys, monkeypatch):
    path = tmp_path / "loop.npz"
    frames = loop.frames[:20]
    np.savez(path, rf=frames.astype(np.float32), spacing=np.array(loop.spacing), origin=np.array(loop.origin))
    out = tmp_path / "out"
    # interrupted while the second pair's result is written: the first pair is kept, the torn file is not trusted
    seen = []
    torn = tear_atomic_write(monkeypatch, lambda p: p.name.startswith("pair_") and (seen.append(p) or len(seen) > 1))
    assert main(["elastogram", str(path), "-o", str(out), "--no-progress"]) == 130
    monkeypatch.undo()
    assert torn
    kept = {p.name: p.stat().st_mtime_ns for p in (out / "pairs").glob("pair_*.npz")}
    assert len(kept) == 1
    assert main(["elastogram", str(path), "-o", str(out), "--no-progress", "--resume"]) == 0
    assert all((out / "pairs" / k).stat().st_mtime_ns == v for k, v in kept.items())     # not recomputed
    with open(out / "pairs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == PAIR_COLUMNS and len(rows) == len(frames) - 1
    assert sum(int(r["selected"]) for r in rows) >= 2
    with np.load(out / "elastogram.npz") as z:
        assert {"exx", "ref_frame", "quality", "spacing"} <= set(z.files)
        assert z["exx"].shape == frames.shape[1:] and 0 <= int(z["ref_frame"]) < len(frames)
    assert (out / "elastogram.png").stat().st_size > 0
    assert (out / "strain_cine.mp4").exists() or (out / "strain_cine.gif").exists()
    # the elastogram's strain ratio over the inclusion (femreg measure) against the true pattern's on the same pixels
    capsys.readouterr()
    tis = loop.tissue
    inc = [tis.inclusion_depth_mm, tis.inclusion_lateral_mm, tis.inclusion_radius_mm]
    assert main(["measure", str(out / "elastogram.npz"), "--inclusion"] + [str(v) for v in inc]
                + ["--json", str(tmp_path / "m.json")]) == 0
    import json

    m = json.loads((tmp_path / "m.json").read_text())
    with np.load(out / "elastogram.npz") as z:
        cov, k = np.isfinite(z["exx"]), int(z["ref_frame"])
    P = loop.pixel_points()
    pat = loop.strain_pattern(k, P).reshape(cov.shape)
    disk = (((P[:, 0] - inc[0]) ** 2 + (P[:, 1] - inc[1]) ** 2) < inc[2] ** 2).reshape(cov.shape)
    sr_true = float(np.mean(pat[cov & ~disk]) / np.mean(pat[cov & disk]))
    # measured 1.39 against 1.49 (6.6 % low: the registration smooths the rim); bound 10 %
    assert m["kind"] == "elastogram" and abs(m["SR"] / sr_true - 1) < 0.10, (m["SR"], sr_true)
    # plot / invert name what the file is and what reads it
    assert main(["plot", str(out / "elastogram.npz"), "-o", str(tmp_path / "e.png")]) == 2
    assert "femreg measure" in capsys.readouterr().err
    # a second run into the same folder without --resume is refused (exit 2), as is bad input
    capsys.readouterr()
    assert main(["elastogram", str(path), "-o", str(out), "--no-progress"]) == 2
    assert "already holds" in capsys.readouterr().err
    # a resume with another band keeps the screening and chooses (and registers) the pairs again
    screen_t = (out / "screen.npz").stat().st_mtime_ns
    rc = main(["elastogram", str(path), "-o", str(out), "--no-progress", "--resume", "--band", "0.3", "3"])
    assert rc in (0, 1)
    assert (out / "screen.npz").stat().st_mtime_ns == screen_t
    again = {p.name: p.stat().st_mtime_ns for p in (out / "pairs").glob("pair_*.npz")}
    assert again and not any(kept.get(k) == v for k, v in again.items())          # none kept from the old band
    with open(out / "pairs.csv") as fh:
        assert sum(int(r["selected"]) for r in csv.DictReader(fh)) >= 1
    # what the screening depends on cannot change on a resume: the message says what was recorded
    capsys.readouterr()
    assert main(["elastogram", str(path), "-o", str(out), "--no-progress", "--resume", "-r", "strain"]) == 2
    assert "regularizer: 'momentum-stress' recorded" in capsys.readouterr().err


def test_bad_input_and_nothing_usable(loop, tmp_path, capsys):
    bad = loop.frames[:6].copy()
    bad[3] = 0.0
    p = tmp_path / "zero.npy"
    np.save(p, bad)
    sp = ["--spacing", str(loop.spacing[0]), str(loop.spacing[1]), "--no-progress"]
    assert main(["elastogram", str(p), "-o", str(tmp_path / "o1")] + sp) == 2
    assert "frame 3" in capsys.readouterr().err
    sat = loop.frames[:6].copy()
    sat[2] = np.clip(sat[2], -1e-3, 1e-3)
    with pytest.raises(InputError, match="saturated"):
        elastogram(sat, spacing=loop.spacing)
    with pytest.raises(InputError, match="band"):
        elastogram(loop.frames[:6], spacing=loop.spacing, band=(0.02, 0.01))
    for a in ("auto", -1.0, float("nan"), [1.0, 2.0]):      # one weight for the whole loop, never a rule
        with pytest.raises(InputError, match="alpha"):
            elastogram(loop.frames[:6], spacing=loop.spacing, alpha=a)
    # a still probe: nothing in the band, computed but nothing usable -> exit 1
    still = np.repeat(loop.frames[:1], 6, axis=0) + 0.01 * np.random.default_rng(0).standard_normal((6,) + loop.frames.shape[1:])
    p = tmp_path / "still.npy"
    np.save(p, still)
    assert main(["elastogram", str(p), "-o", str(tmp_path / "o2")] + sp) == 1
    cap = capsys.readouterr()
    assert "no pair was usable" in cap.err
    assert "no elastogram" in cap.out and "best elastogram" not in cap.out, cap.out


def test_two_worker_processes_screen_identically_and_register_alike(loop, run):
    serial, _ = run
    par = elastogram(loop.frames, spacing=loop.spacing, origin=loop.origin, workers=2)
    for k in ("strain", "lateral_mm", "ncc"):                 # the same computation, split into runs of pairs
        assert np.array_equal(par.screen[k], serial.screen[k]), k
    key = [(r["ref"], r["mov"], r["registered"], r["usable"]) for r in serial.pairs]
    assert [(r["ref"], r["mov"], r["registered"], r["usable"]) for r in par.pairs] == key
    # the first pair of the second run starts from the pyramid, not warm: measured 1e-4 relative (seed 6)
    for a, b in zip(serial.pairs, par.pairs):
        if a["usable"]:
            assert abs(b["strain"] - a["strain"]) <= 1e-3 * abs(a["strain"]), (a, b)
    e_s, e_p = (_normalised_error(loop, r.exx, r.ref_frame) for r in (serial, par))
    assert par.ref_frame == serial.ref_frame and abs(e_p - e_s) <= 0.1, (e_s, e_p)
    with pytest.raises(InputError, match="workers"):
        elastogram(loop.frames[:6], spacing=loop.spacing, workers=0)


def test_band_advice_names_the_band_the_loop_reaches():
    """No pair in the band: the advice names the largest strain the loop reaches (accumulated over at most
    max_span frames) and a band that holds it, or the smallest step when every step overshoots; nothing to say
    when the band was reachable."""
    from femreg.elastogram import band_advice

    slow = band_advice({"strain": np.full(5, -0.0007)})                # 6 frames, -0.35 % from first to last
    assert "-0.35 % (frames 0 -> 5)" in slow and "--band 0.25 2" in slow and "max-span" not in slow, slow
    long = band_advice({"strain": np.full(20, -0.0004)}, max_span=8)    # spans cap the strain: longer ones help
    assert "-0.32 %" in long and "--max-span" in long, long
    fast = band_advice({"strain": np.full(4, 0.03)})
    assert "smallest axial strain is 3.00 %" in fast and "--band 0.5 4" in fast, fast
    assert band_advice({"strain": np.full(5, -0.003)}) == ""            # 0.6 % over two frames: reachable


def test_picture_colour_bars_clear_of_the_next_panel(loop, run):
    # elastogram.png: each colour bar with its label ends left of the next panel's depth label (they collided)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from femreg.cli.elastogram_cmd import elastogram_figure

    res = run[0]
    fig = elastogram_figure(res, np.asarray(loop.frames[res.ref_frame], float), loop.spacing, loop.origin)
    r = fig.canvas.get_renderer()
    panels = [a for a in fig.axes if a.child_axes]
    assert len(panels) == 3
    for left, right in zip(panels[:-1], panels[1:]):
        reach = max(c.get_tightbbox(r).x1 for c in left.child_axes)
        assert reach < right.get_tightbbox(r).x0, "colour bar label over the next panel"
    plt.close(fig)


def test_bmode_loop_in_a_fan_covers_the_whole_fan(loop, tmp_path):
    """The loop as a convex probe's display shows it: 8-bit B-mode inside a fan, black wedges fixed on the screen.
    Screened whole, the wedges' match read 4.6-5.5 % strain on the first consecutive pairs and no pair was
    usable.  The fan is kept whole (as femreg.register does): screened on the windows that see no fill,
    registered with the fill weighted 0 in eq:IR, NaN outside.  Measured (benchmarks/elastogram_fan.py, seed 6):
    82.1 % of the fan covered (the rest: the mesh margin) at 15.0 % normalised strain error; on the largest
    rectangle without fill (before) 36.3 % at 21.7 %.  Bounds 75 % and 17 %."""
    from forward.display import bmode_uint8, sector_fan

    bm = bmode_uint8(np.asarray(loop.frames[:16], float), axis=1)
    n, m = bm.shape[1:]
    # an apex 8 mm above the first row, 74 % of the frame
    fan = sector_fan((n, m), loop.spacing, apex_mm=8.0, top_half_width_mm=0.2 * m * loop.spacing[1])
    bm[:, ~fan] = 0
    res = elastogram(bm, spacing=loop.spacing, origin=loop.origin, output_dir=tmp_path / "fan")
    assert res.region is not None and "fill of value 0" in res.excluded and "NaN outside the fan" in res.excluded
    (a, b), (c, d) = res.region
    assert res.exx.shape == (b - a, d - c)
    np.testing.assert_array_equal(res.data_mask, fan[a:b, c:d])
    full = np.full(fan.shape, np.nan)
    full[a:b, c:d] = res.exx
    ok = np.isfinite(full)
    assert not np.any(ok & ~fan) and not np.any(res.quality[~res.data_mask] > 0)
    assert np.all(np.isnan(res.cine[:, ~res.data_mask[::round(res.cine_spacing[0] / loop.spacing[0])]]))
    assert ok[fan].mean() > 0.75, ok[fan].mean()
    assert res.n_usable >= 2, res.pairs
    for r in res.pairs:
        if r["usable"]:
            assert DEFAULT_BAND[0] <= abs(r["strain"]) <= DEFAULT_BAND[1], r
    assert _normalised_error(loop, full, res.ref_frame) < 17.0
    # the same fan given: the same elastogram, with nothing detected
    given = elastogram(bm, spacing=loop.spacing, origin=loop.origin, data_mask=fan)
    np.testing.assert_array_equal(given.exx, res.exx)
    assert "outside the given data_mask" in given.excluded
    # the command writes the fan with the elastogram; its pictures are empty outside it
    path = tmp_path / "fan.npz"
    np.savez(path, frames=bm, spacing=np.asarray(loop.spacing), origin=np.asarray(loop.origin))
    assert main(["elastogram", str(path), "-o", str(tmp_path / "cli"), "--no-progress"]) == 0
    with np.load(tmp_path / "cli" / "elastogram.npz") as z:
        np.testing.assert_array_equal(z["data_mask"], res.data_mask)
        np.testing.assert_array_equal(z["region"], res.region)
        assert np.all(np.isnan(z["exx"][~z["data_mask"]])) and np.isfinite(z["exx"][z["data_mask"]]).mean() > 0.75
    assert (tmp_path / "cli" / "elastogram.png").exists()


def test_roi_cuts_the_loop_like_register(loop, tmp_path, capsys):
    """--roi is honoured: the loop is screened and registered on the rectangle (widened by the mesh margin), the
    elastogram lies on its pixels with the region recorded, and what was left out is said.  Before, the flag was
    taken but the pairs' registration refused it (a user mesh excludes a roi) after the screening."""
    frames = loop.frames[:20]
    path = tmp_path / "loop.npz"
    np.savez(path, rf=frames.astype(np.float32), spacing=np.array(loop.spacing), origin=np.array(loop.origin))
    x0, y0 = (float(o) for o in loop.origin)
    n, m = frames.shape[1:]
    # the middle of the image: a quarter of the depth and of the width left out on each side
    dx, dy = (float(s) for s in loop.spacing)
    roi = (x0 + 0.25 * n * dx, x0 + 0.75 * n * dx, y0 + 0.25 * m * dy, y0 + 0.75 * m * dy)
    out = tmp_path / "roi"
    rc = main(["elastogram", str(path), "-o", str(out), "--no-progress", "--roi", *(f"{v:.4f}" for v in roi)])
    said = capsys.readouterr().out
    assert rc == 0 and "left out of the mesh (the rest is registered): outside the given roi" in said, said
    with np.load(out / "elastogram.npz") as z:
        (a, b), (c, d) = z["region"]
        exx, origin = z["exx"], z["origin"]
    # measured: 62 % of the region covered (2 usable pairs); bound 40 %
    assert exx.shape == (b - a, d - c) and np.isfinite(exx).mean() > 0.4
    # the region holds the roi, widened by the mesh margin (measured rows 130-598 for 182-545, lines 10-51 for
    # 15-45): at most a tenth of the image on each side
    assert a <= 0.25 * n + 1 and b >= 0.75 * n - 1 and (b - a) <= 0.5 * n + 2 * 0.1 * n, (a, b, n)
    assert c <= 0.25 * m + 1 and d >= 0.75 * m - 1 and (d - c) <= 0.5 * m + 2 * 0.1 * m, (c, d, m)
    assert origin == pytest.approx((x0 + a * dx, y0 + c * dy))
    with pytest.raises(InputError, match="leaves the image"):
        elastogram(frames, spacing=loop.spacing, origin=loop.origin, roi=(x0 - 5.0, x0 + 1.0, y0, y0 + 1.0))
