"""The inversion benchmark's contrast metric: a ring (1.6-2.5 R) mostly outside the image is reported as not
measurable and left out of the band count, not silently dropped.  No registration or inversion runs."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import inversion as B  # noqa: E402


def _inside_28mm(points):
    """1 inside the benchmark's 28 x 28 mm inversion mesh (depth x 6-34 mm, |y| <= 14 mm), NaN outside, as
    ``shear_modulus``."""
    return np.where((np.abs(points[:, 1]) <= 14.0) & (points[:, 0] >= 6.0) & (points[:, 0] <= 34.0), 1.0, np.nan)


def test_ring_coverage_of_a_large_disk_in_a_narrow_image():
    # the fresh3 disks at 20 mm depth on their registration meshes: radius 8 37 % of the ring's samples inside,
    # radius 7 64-66 %, radius 6 93-94 %; this idealised mesh gives 38 %, 67 %, 95 %
    cover = {R: B.ring_coverage(_inside_28mm, (20.0, 0.0), R) for R in (6.0, 7.0, 8.0)}
    assert abs(cover[8.0] - 0.37) < 0.03 and cover[8.0] < B.RING_MEASURABLE
    assert cover[7.0] > B.RING_MEASURABLE and cover[6.0] > 0.9


def _row(case, ratio, ring, success=True):
    return dict(case=case, row="femreg", ratio=ratio, estimate=ratio * 2.0, contrast=2.0, success=success,
                ring=ring, cv=0.05, z=[0.5], misfit=1e-3, seconds=1.0, n_el=10, ncal=0, cal=np.nan, ncalu=0,
                calu=np.nan, radius=5.0, snr=20.0, chosen_model="plane-strain", beta=0.01, flags="")


def test_summary_reports_and_excludes_an_unmeasurable_ring():
    rows = [_row("a", 1.0, 1.0), _row("b", 1.3, 0.37), _row("c", 0.8, 0.9)]
    rows += [dict(r, row="1/SR", ratio=0.5) for r in rows]
    text = B.summary(rows, "s")
    assert "1/2 unflagged with ratio 0.85-1.15" in text
    assert "ring not measurable" in text and "b (ring 37 % inside, ratio 1.30)" in text
    assert "counting every case: 1/3" in text
    assert "(ring not measurable)" in B.table(rows)


def test_debias_study_counts_stiff_cases_closer_than_1_over_sr(tmp_path, capsys):
    from benchmarks import inversion_debias_study as D

    def row(case, contrast, ratio, sr_ratio, success=True, ring=1.0):
        return dict(set="s", case=case, contrast=contrast, estimate=ratio * contrast, ratio=ratio, cv=0.05,
                    ring=ring, success=success, z=[0.5], seconds=1.0, sr=sr_ratio * contrast)
    # closer; farther (1/SR 0.95 against 0.9); flagged (a miss); unmeasurable ring (left out); soft (not counted)
    rows = [row("a", 4.0, 0.95, 0.6), row("b", 2.0, 0.9, 0.95), row("c", 3.0, 1.0, 0.6, success=False),
            row("d", 4.0, 1.0, 0.6, ring=0.3), row("e", 0.25, 1.0, 2.4)]
    p = tmp_path / "rows.json"
    p.write_text(__import__("json").dumps(rows))
    D.summary([p])
    out = capsys.readouterr().out
    assert "- s: " in out and "stiff closer than 1/SR 1/3" in out


def test_ring_parts_separates_caps_from_sides():
    from benchmarks import inversion_debias_study as D

    # 2 in the caps (|dx| > |dy|, x axial), 1 at the sides: caps / sides 2, each part flat
    fun = lambda q: np.where(np.abs(q[:, 0] - 20.0) > np.abs(q[:, 1]), 2.0, 1.0)  # noqa: E731
    cv, caps_over_sides, cv_caps, cv_sides = D.ring_parts(fun, (20.0, 0.0), 5.0)
    assert abs(caps_over_sides - 2.0) < 1e-12 and cv_caps < 1e-12 and cv_sides < 1e-12 and cv > 0.3
