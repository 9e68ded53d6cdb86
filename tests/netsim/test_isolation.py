"""netsim stands alone: no module of it imports the suite, the methods or the reports."""

import ast
from pathlib import Path

import netsim

FORBIDDEN = ("suite", "methods", "reports")
PACKAGE_DIR = Path(netsim.__file__).parent


def _imported_modules(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None))
              in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)):
            yield node.lineno, node.args[0].value  # importlib.import_module("suite...") counts too


def test_no_netsim_module_imports_suite_methods_or_reports():
    modules = sorted(PACKAGE_DIR.rglob("*.py"))
    assert len(modules) >= 10
    offenders = []
    for path in modules:
        tree = ast.parse(path.read_text(), filename=str(path))
        for lineno, name in _imported_modules(tree):
            if name.split(".")[0] in FORBIDDEN:
                offenders.append(f"{path.relative_to(PACKAGE_DIR.parent)}:{lineno} imports {name}")
    assert not offenders, "netsim must stand alone: " + "; ".join(offenders)


def test_netsim_error_is_a_value_error_with_a_one_line_message():
    error = netsim.NetsimError("bad\n   setting  here")
    assert isinstance(error, ValueError) and str(error) == "bad setting here"
