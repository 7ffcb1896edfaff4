"""The volume pipeline's functions read every parameter they take: a parameter left unread (coarse_to_fine's
``period`` was passed by register_volume and never used) tells callers that it steers something it does not."""
import ast
from pathlib import Path

import pytest

import femreg

MODULES = ("volume.py", "volume_refine.py", "volume_fields.py", "volume_result.py", "echo_volume.py", "swept.py")


def _unread(path: Path) -> list:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        if all(isinstance(b, (ast.Expr, ast.Pass, ast.Raise)) for b in node.body):
            continue            # a docstring-only or abstract method: its signature is an interface
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        if "locals" in names:   # the parameters read as a whole
            continue
        params = [a.arg for a in node.args.posonlyargs + node.args.args + node.args.kwonlyargs]
        out += [f"{path.name}:{node.lineno} {node.name}({a})" for a in params
                if a not in ("self", "cls") and not a.startswith("_") and a not in names]
    return out


@pytest.mark.parametrize("module", MODULES)
def test_every_parameter_is_read(module):
    assert _unread(Path(femreg.__file__).parent / module) == []


def test_the_check_finds_an_unread_parameter(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("def f(a, *, period=None, at=None):\n    return a + at\n")
    assert _unread(src) == ["m.py:1 f(period)"]
