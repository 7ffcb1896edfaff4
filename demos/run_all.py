"""Run every numbered demo (demos/NN_*.py) in order; each writes into out/<demo name>/.

Usage: python demos/run_all.py [--quick] [--full-study]

The study demo (06) runs its quick version unless --full-study is given (the full study takes about 11 min on
2 cores from an empty cache; `make study`).
"""
import subprocess
import sys
import time
from pathlib import Path

here = Path(__file__).resolve().parent
quick = "--quick" in sys.argv[1:]
full_study = "--full-study" in sys.argv[1:]
demos = sorted(p for p in here.glob("[0-9][0-9]_*.py"))
failed = []
for demo in demos:
    t0 = time.perf_counter()
    print(f"=== {demo.name}", flush=True)
    q = quick or ("study" in demo.name and not full_study)
    rc = subprocess.call([sys.executable, str(demo)] + (["--quick"] if q else []), cwd=here.parent)
    print(f"=== {demo.name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {time.perf_counter() - t0:.1f} s",
          flush=True)
    if rc:
        failed.append(demo.name)
sys.exit(1 if failed else 0)
