"""Every third-party module the package imports is a declared dependency (issue #12: click
was imported but not declared, and a fresh install failed)."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NEWER_STDLIB = {"compression"}
"""Standard-library packages of a newer Python than the oldest supported, imported only on
that Python (3.14's ``compression.zstd``; its backport is declared for the older ones)."""


def _imported_top_level(root: Path) -> dict[str, str]:
    """Top-level module name -> first file importing it (absolute imports only)."""
    found: dict[str, str] = {}
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], str(path.relative_to(REPO)))
    return found


def _declared(*extras: str) -> set[str]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in extras:
        reqs += project["optional-dependencies"][extra]
    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].strip().lower().replace("_", "-")
            for r in reqs}


def _own_modules() -> set[str]:
    """The project's own top-level modules: the package and its ``py-modules`` (the console
    entry point ``_adalio_entry``)."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    return {"adalio", *tool.get("py-modules", [])}


def _undeclared(root: Path, declared: set[str]) -> list[str]:
    dists = packages_distributions()
    own = _own_modules()
    missing = []
    for module, where in _imported_top_level(root).items():
        if module in sys.stdlib_module_names | NEWER_STDLIB or module in own \
                or module == "__future__":
            continue
        names = {d.lower().replace("_", "-") for d in dists.get(module, [module])}
        if not names & declared:
            missing.append(f"{module} (imported in {where}, distribution {sorted(names)})")
    return missing


def test_every_package_import_is_a_declared_dependency():
    """Runtime dependencies, or the optional extra of a feature imported only where it is
    used (rerun-sdk for --view is in [view])."""
    assert _undeclared(REPO / "src", _declared("view")) == []


def test_every_test_import_is_declared_in_the_test_extra():
    """The repository's own scripts a test imports (``tests/``, and ``benchmarks/`` for a
    benchmark's measuring function) are not distributions."""
    local = {p.stem for d in ("tests", "benchmarks") for p in (REPO / d).rglob("*.py")}
    missing = [m for m in _undeclared(REPO / "tests", _declared("test"))
               if m.split(" ")[0] not in local]
    assert missing == []


def test_lower_bounds_on_every_dependency():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for extra in project["optional-dependencies"]
                                            .values() for r in extra]
    assert [r for r in reqs if ">=" not in r] == []
