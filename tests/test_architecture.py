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


# -- the import graph of femreg ----------------------------------------------------------------------------------

def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _import_graph(package: str = "femreg") -> dict:
    """{module: {imported femreg modules}} from the source: every import statement, at module level or inside a
    function, relative ones resolved.  ``from a import b`` counts as an import of ``a.b`` when that is a module,
    else of ``a``; a parent package's ``__init__`` (run by Python before any submodule) is not counted, so an
    edge means "this module's code names that module"."""
    import ast

    files = {_module_name(p): p for p in (ROOT / package).rglob("*.py")}
    graph = {}
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        base = mod.split(".") if is_pkg else mod.split(".")[:-1]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    stem = base[:len(base) - node.level + 1]
                    target = ".".join(stem + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                targets = []
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    targets.append(sub if sub in files else target)
            else:
                continue
            deps.update(t for t in targets if t in files and t != mod)
        graph[mod] = deps
    return graph


def _cycles(graph: dict) -> list:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_import_graph_sees_function_level_and_relative_imports():
    g = _import_graph()
    # a module-level relative import, a function-level one, and "from . import submodule"
    assert "femreg.solver" in g["femreg.registration"], g["femreg.registration"]
    assert "femreg.cli._common" in g["femreg.cli.register_cmd"]
    assert "femreg._kernels" in g["femreg.data_term"] and "femreg" not in g["femreg.data_term"]
    assert any("femreg.plot" in deps for deps in g.values())
    # the cycle finder finds a planted cycle, through a third module
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_inside_femreg():
    cycles = _cycles(_import_graph())
    assert not cycles, f"import cycles (counting imports inside functions): {cycles}"


#: The femreg modules other packages (forward, paperstudy) may import from: the package and its user-facing
#: modules, not the stages of a registration (pyramid, initial, gnsolve, repair, pixels, data_term, solver, ...).
PUBLIC_MODULES = {"femreg", "femreg.errors", "femreg.io", "femreg.plot", "femreg.speckle", "femreg.metrics",
                  "femreg.mesh", "femreg.regularizers", "femreg.inversion", "femreg.autoalpha", "femreg.batch",
                  "femreg.sequence", "femreg.quality", "femreg.synthetic", "femreg.registration", "femreg.result",
                  "femreg.optional", "femreg.echo", "femreg.orientation", "femreg.elastogram", "femreg.progress"}


def _femreg_imports(package: str):
    """(file, line, module, name) of every import of femreg in ``package`` (module level and inside functions)."""
    import ast

    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] == "femreg":
                        yield path.name, node.lineno, a.name, None
            elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "femreg":
                for a in node.names:
                    yield path.name, node.lineno, node.module, a.name


def _public_violations(package: str) -> list:
    import importlib

    bad = []
    for fname, line, module, name in _femreg_imports(package):
        where = f"{package}/{fname}:{line}"
        if module not in PUBLIC_MODULES:
            bad.append(f"{where}: {module} is not a public module")
            continue
        if name is None:
            continue
        mod = importlib.import_module(module)
        sub = f"{module}.{name}"
        if not (name in getattr(mod, "__all__", ()) or sub in PUBLIC_MODULES):
            bad.append(f"{where}: {module}.{name} is not in {module}.__all__")
    return bad


def test_public_import_check_catches_private_names(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "a.py").write_text("from femreg._atomic import atomic_savez\nfrom femreg.pyramid import envelope\n"
                              "def f():\n    from femreg.io import _not_there\n"
                              "    from femreg.speckle import envelope\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    bad = _public_violations("pkg")
    assert len(bad) == 3 and "femreg._atomic" in bad[0] and "femreg.pyramid" in bad[1] and "_not_there" in bad[2], bad


def test_forward_and_paperstudy_use_public_femreg_names_only():
    for package in ("forward", "paperstudy"):
        assert not _public_violations(package), _public_violations(package)


def test_register_is_an_orchestrator_of_its_stage_modules():
    import ast
    import inspect

    import femreg.registration as R

    src = inspect.getsource(R.register)
    fn = ast.parse(src).body[0]
    body = fn.body[1:] if isinstance(fn.body[0], ast.Expr) else fn.body      # without the docstring
    n_lines = body[-1].end_lineno - body[0].lineno + 1
    assert n_lines <= 100, f"register's body is {n_lines} lines: move the stage's work into its module"
    called = {n.func.id for n in ast.walk(fn) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert {"_validate", "_mesh_stage", "initial_guess", "solve", "repair_peak_hopping", "check_result"} <= called


def test_no_cache_keyed_by_object_id():
    import ast

    for path in sorted((ROOT / "femreg").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "id":
                raise AssertionError(f"{path.relative_to(ROOT)}:{node.lineno}: id() (objects' ids are reused)")


def test_batch_is_split_by_job_and_keeps_its_public_names():
    import femreg.batch as B

    names = ["Task", "TaskOutcome", "run_tasks", "open_client", "Job", "jobs_from_inputs", "run_batch",
             "BatchSummary", "default_settings", "settings_keys", "settings_file_for", "MANIFEST", "flag_defaults",
             "frames_text", "run_recording_task"]
    assert all(hasattr(B, n) for n in names), [n for n in names if not hasattr(B, n)]
    homes = {B.run_tasks: "engine", B.default_settings: "settings", B.jobs_from_inputs: "inputs",
             B.run_batch: "running", B.BatchSummary: "summary"}
    for obj, mod in homes.items():
        assert obj.__module__ == f"femreg.batch.{mod}", (obj, obj.__module__)
    assert "femreg.cli._common" not in _import_graph()["femreg.batch.settings"]   # the library owns the schema


def test_cli_defaults_are_the_librarys():
    import argparse
    import inspect

    import femreg
    from femreg.batch import default_settings
    from femreg.cli._common import add_registration_args

    p = argparse.ArgumentParser()
    add_registration_args(p)
    parsed = vars(p.parse_args([]))
    sig = inspect.signature(femreg.register).parameters
    for k in ("regularizer", "strategy", "maxiter", "tol"):
        assert parsed[k] == sig[k].default == default_settings()[k], k
