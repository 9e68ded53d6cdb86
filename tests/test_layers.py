"""The layering shows in the folders and is enforced here (an import-linter-style contract on the AST):

* ``suite.core`` (rendering) never imports the harness, netsim, methods or reports;
* ``netsim`` imports neither ``suite`` nor ``methods`` nor ``reports``;
* ``suite.harness`` never imports ``methods`` (methods are discovered as plugins) nor ``reports``, except its
  CLI, the application's entry point, which builds the report;
* ``reports`` only read results: they import no rendering, tracing, runner or executor module;
* a method imports no other method.
"""
import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def _violations(folder: str, forbidden: tuple[str, ...], repo: Path = REPO) -> list[str]:
    out = []
    for path in sorted((repo / folder).rglob("*.py")):
        if path.relative_to(repo).as_posix() in EXEMPT.get(forbidden, ()):
            continue
        for name in sorted(_imports(path)):
            if any(name == f or name.startswith(f + ".") for f in forbidden):
                out.append(f"{path.relative_to(repo)} imports {name}")
    return out


HARNESS_FORBIDDEN = ("methods", "reports")
EXEMPT = {HARNESS_FORBIDDEN: ("suite/harness/cli.py",)}
RULES = [
    ("suite/core", ("suite.harness", "netsim", "methods", "reports")),
    ("netsim", ("suite", "methods", "reports")),
    ("suite/harness", HARNESS_FORBIDDEN),
    ("reports", ("suite.core.trace", "suite.core.scene", "suite.core.gbuffer", "suite.core.shading",
                 "suite.core.reference", "suite.harness.runner", "suite.harness.executor", "suite.harness.timeline")),
]


@pytest.mark.parametrize("folder,forbidden", RULES, ids=[r[0] for r in RULES])
def test_layer_imports(folder, forbidden):
    assert _violations(folder, forbidden) == []


def test_methods_do_not_import_each_other():
    problems = []
    for method_dir in sorted(p for p in (REPO / "methods").iterdir() if p.is_dir() and p.name != "__pycache__"):
        others = tuple(f"methods.{p.name}" for p in (REPO / "methods").iterdir()
                       if p.is_dir() and p.name not in (method_dir.name, "__pycache__"))
        problems += _violations(f"methods/{method_dir.name}", others) if others else []
    assert problems == []


def test_the_check_can_fail(tmp_path):
    bad = tmp_path / "suite" / "core"
    bad.mkdir(parents=True)
    (bad / "x.py").write_text("from suite.harness import runner\n")
    assert _violations("suite/core", ("suite.harness",), tmp_path) == ["suite/core/x.py imports suite.harness",
                                                             "suite/core/x.py imports suite.harness.runner"]
