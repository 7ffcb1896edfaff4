"""Package boundaries: the registration library (femreg) never imports the simulator (forward) or the paper study
(paperstudy); those contribute their subcommands to the `femreg` CLI through the ``femreg.commands`` entry points."""
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=ROOT,
                          env={"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin", "HOME": str(Path.home()),
                               "PYTHONPATH": str(ROOT)})


def test_femreg_and_every_submodule_import_without_forward():
    r = _run("""
        import importlib, pkgutil, sys
        import femreg
        names = [m.name for m in pkgutil.walk_packages(femreg.__path__, "femreg.")
                 if not m.name.endswith("__main__")]
        for n in names:
            importlib.import_module(n)
        from femreg.cli import main
        try:
            main(["register", "--help"])
        except SystemExit:
            pass
        bad = sorted(m for m in sys.modules if m.split(".")[0] in ("forward", "paperstudy"))
        print("RESULT", len(names), bad)
        assert not bad, bad
    """)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    n = int(r.stdout.split("RESULT")[-1].split()[0])
    assert n > 30, f"only {n} femreg submodules found: the walk did not see the package"


def test_contributed_subcommands_are_listed_and_loaded_lazily():
    from femreg.cli import _contributed

    names = set(_contributed())
    assert {"simulate", "forward", "study"} <= names, (
        f"entry points {sorted(names)}: reinstall the package (pip install -e .) after changing pyproject.toml")
    r = _run("""
        import sys
        from femreg.cli import main
        try:
            main(["--help"])
        except SystemExit:
            pass
    """)
    for cmd in ("register", "track", "study", "simulate", "forward"):
        assert f"    {cmd}" in r.stdout, (cmd, r.stdout)
