"""3D against 2D registration on the paper's 3D HI phantom imaged as RF volumes (benchmarks/volume_study.py).

Slow: the first run renders the volume sequence (minutes, cached); the quick crop (20-42 x +-11 x +-5 mm around
the sphere) then registers in about 10-20 s of wall time on the shared 2-core machine.  Bounds are the values
measured with the default settings (docs/study_report.md, section "3D against 2D on the paper's 3D phantom") plus
the stated margins, so a regression of the 3D path on the paper's phantom fails.
"""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Measured on the quick crop (femreg's defaults: 2 mm elements refined, momentum-stress; paperstudy/volume_runs/
#: quick_refine.json): 3D in-plane total strain error 20.33 % (its mesh floor, the truth at the hexahedral nodes:
#: 19.82 %), u_y 4.63 %, u_z 24.21 %, six-component 22.53 %; 2D on the central plane: 20.67 %, u_y 10.52 %.
MEASURED = {"e": 20.33, "uy": 4.63, "uz": 24.21, "e6": 22.53}
#: Margin on each bound: 5 % of the measured value plus 0.5 points (seeded data, deterministic solver; the margin
#: covers BLAS / solver-order differences between machines).
REL, ABS = 0.05, 0.5


def _study():
    spec = importlib.util.spec_from_file_location("volume_study", REPO / "benchmarks" / "volume_study.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_quick_crop_3d_registration_bounded_by_measured(tmp_path):
    out = tmp_path / "quick.json"
    assert _study().main(["--quick", "--no-inversion", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    r3 = r["3d"]
    assert r3 is not None and r3["success"], r3
    for key, v in MEASURED.items():
        assert r3[key] <= v * (1 + REL) + ABS, (key, r3[key], v)
    # the 3D registration measures the lateral displacement better than the 2D one on the same plane
    assert r3["uy"] < r["2d"]["uy"] - 2.0
    # the 3D registration sits within a point of its own (refined) mesh floor (measured 0.51)
    assert r3["e"] - r3["floor_e"] < 1.0, (r3["e"], r3["floor_e"])
    # axial displacement: both well below 1 %
    assert r3["ux"] < 0.5 and r["2d"]["ux"] < 0.5


def test_section_from_records(tmp_path):
    """The report section is written from the JSON records and replaces its marked block on a rerun."""
    mod = _study()
    rec = {"crop_mm": None, "element_size_mm": None, "shape": [10, 5, 3], "spacing": [0.02, 0.3, 0.5],
           "2d": {"ux": 0.1, "uy": 9.0, "e": 9.5, "floor_e": 8.0, "time_s": 1.0, "cpu_s": 1.0, "peak_rss_mb": 10.0},
           "3d": {"ux": 0.1, "uy": 5.0, "uz": 20.0, "e": 7.0, "e6": 8.0, "time_s": 2.0, "cpu_s": 2.0,
                  "peak_rss_mb": 20.0},
           "inversion_region_mm": [15, 45, -15, 15, -8, 8],
           "inversion": {"3d_registered": {"contrast": 3.5, "ring_contrast": None, "cv_background": 0.1,
                                           "beta": 1e-3, "elements": 100, "success": True, "time_s": 1.0},
                         "3d_exact": {"contrast": 4.1, "ring_contrast": None, "cv_background": 0.1, "beta": 1e-3,
                                      "elements": 100, "success": True, "time_s": 1.0},
                         "2d_exact": {"contrast": 2.2, "ring_contrast": 2.1, "cv_background": 0.2, "beta": 0.01,
                                      "elements": 50, "success": True, "time_s": 1.0},
                         "2d_registered": {"contrast": 2.0, "ring_contrast": 2.1, "cv_background": 0.2,
                                           "beta": 0.01, "elements": 50, "success": False, "time_s": 1.0}}}
    report = tmp_path / "report.md"
    report.write_text("# report\n\ntext\n")
    frag = tmp_path / "section.md"
    mod.write_section(frag, [rec], into=report)
    text = report.read_text()
    assert text.startswith("# report\n\ntext\n") and text.count(mod.BEGIN) == 1
    assert "in-plane total strain error on the central plane, 3D 7.0 %" in text and "**NOT met**" in text
    assert "contrast 3.50" in text and "2.00*" in text
    rec["3d"]["e"] = 5.0
    mod.write_section(frag, [rec], into=report)
    text = report.read_text()
    assert text.count(mod.BEGIN) == 1 and text.count(mod.END) == 1 and "3D 5.0 %" in text
    assert frag.read_text().strip() == text[text.index(mod.BEGIN):].strip()


def test_report_carries_the_generated_section():
    """docs/study_report.md holds the block that volume_study.py wrote to paperstudy/volume_section.md, and the
    study's report generator carries that file into every report it writes."""
    from paperstudy.study import VOLUME_SECTION, _volume_section

    mod = _study()
    frag = VOLUME_SECTION.read_text()
    assert frag.startswith(mod.BEGIN) and frag.rstrip().endswith(mod.END)
    assert frag.strip() in (REPO / "docs" / "study_report.md").read_text()
    assert _volume_section()[0] == mod.BEGIN


def test_refine_argument_names_the_presets():
    from femreg.volume_refine import PLANE_REFINEMENT, VOLUME_REFINEMENT

    arg = _study()._refine_arg
    assert arg("off") is None and arg("auto") == "auto" and arg("2") == 2
    assert arg("plane") is PLANE_REFINEMENT
    r = arg("plane,max_growth=6,threshold=3")
    assert (r.max_growth, r.threshold, r.plane, r.even) == (6, 3, 0.0, True)
    r = arg("interior=1,max_growth=8")
    assert r.interior and r.max_growth == 8 and r.plane is None and r.min_size == VOLUME_REFINEMENT.min_size
