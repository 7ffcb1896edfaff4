"""Every demo runs in its quick mode (``demos/NN_*.py --quick``, as ``make demo`` runs them), so none can rot.

Each demo runs in a subprocess in a temporary working directory (its figures go to ``out/<demo>/`` there) with
the simulator's usual cache.  Measured here (2 shared cores, warm cache): 01 20 s, 02 20 s, 05 15 s, 07 14 s;
06 (the quick paper study) 160 s, so it is marked slow.  Demos whose quick run already has a test that checks
its results (:data:`DEDICATED`) are run there, not twice.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DEMOS = sorted((ROOT / "demos").glob("[0-9][0-9]_*.py"))
#: Demos whose quick mode takes minutes.
SLOW = {"06_study.py"}
#: Demos run in quick mode by a test that also checks what they write: demo -> (test file, test function).
DEDICATED = {"01_forward.py": ("test_forward.py", "test_demo_01_forward_quick"),
             "07_invivo.py": ("test_invivo.py", "test_demo_quick_writes_summary")}
RUN_HERE = [d for d in DEMOS if d.name not in DEDICATED]


def test_every_demo_is_run_by_a_test():
    assert len(DEMOS) >= 5, DEMOS
    here = Path(__file__).resolve().parent
    for name, (fname, func) in DEDICATED.items():
        assert (ROOT / "demos" / name).exists(), f"{name} is gone: drop it from DEDICATED"
        text = (here / fname).read_text()
        assert f"def {func}(" in text and name in text, f"{fname}::{func} must run demos/{name} --quick"


@pytest.mark.parametrize("demo", [pytest.param(d, marks=pytest.mark.slow) if d.name in SLOW else d
                                  for d in RUN_HERE], ids=[d.stem for d in RUN_HERE])
def test_demo_runs_in_quick_mode(demo, tmp_path):
    env = dict(os.environ, MPLBACKEND="Agg", PYVISTA_OFF_SCREEN="true", OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    r = subprocess.run([sys.executable, str(demo), "--quick"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=1200)
    assert r.returncode == 0, f"{demo.name} --quick exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    if "skipping" in r.stdout:         # a demo on data that is not there (in vivo) says so and exits 0
        return
    written = [p for p in (tmp_path / "out").rglob("*") if p.is_file() and p.stat().st_size > 0]
    assert written, f"{demo.name} wrote nothing under out/:\n{r.stdout[-2000:]}"
