"""The dependency rule, checked on the source: every module's imports parsed with ``ast``.

``frontends`` and ``graph`` are leaves (they never import ``iceg`` or each other),
``iceg_common`` is the shared root (it imports no other project package), and no module imports
a private name (``_name``) or a private module from another package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PROJECT = ("iceg", "graph", "frontends", "iceg_common")
FORBIDDEN = {
    "frontends": {"iceg", "graph"},
    "graph": {"iceg", "frontends"},
    "iceg_common": {"iceg", "graph", "frontends"},
    "iceg": set(),
}


def _modules() -> list[Path]:
    return sorted(p for pkg in PROJECT for p in (REPO / pkg).rglob("*.py"))


def _imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """``(line, imported module, imported names)`` of every absolute import in ``path``."""
    out: list[tuple[int, str, list[str]]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, a.name, []) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module, [a.name for a in node.names]))
    return out


def _package_of(path: Path) -> str:
    """Dotted package (directory) of a source file, e.g. ``iceg.matching``."""
    return ".".join(path.relative_to(REPO).parent.parts)


def test_every_project_package_is_scanned() -> None:
    assert {p.relative_to(REPO).parts[0] for p in _modules()} == set(PROJECT)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(REPO)))
def test_leaves_and_root_import_only_what_the_rule_allows(path: Path) -> None:
    top = path.relative_to(REPO).parts[0]
    bad = [
        f"{path.relative_to(REPO)}:{line}: imports {module}"
        for line, module, _ in _imports(path)
        if module.split(".")[0] in FORBIDDEN[top]
    ]
    assert not bad, "dependency rule broken:\n" + "\n".join(bad)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(REPO)))
def test_no_private_name_crosses_a_package(path: Path) -> None:
    here = _package_of(path)
    bad = []
    for line, module, names in _imports(path):
        if module.split(".")[0] not in PROJECT:
            continue
        parts = module.split(".")
        private_module = any(p.startswith("_") and not p.startswith("__") for p in parts)
        module_package = module if (REPO / Path(*parts)).is_dir() else ".".join(parts[:-1])
        if module_package == here:
            continue
        private_names = [n for n in names if n.startswith("_") and not n.startswith("__")]
        if private_module or private_names:
            bad.append(f"{path.relative_to(REPO)}:{line}: from {module} import {names}")
    assert not bad, "private names imported across packages:\n" + "\n".join(bad)


def test_rule_catches_a_leaf_importing_iceg(tmp_path: Path) -> None:
    """The checker itself: a leaf module that imports iceg is found."""
    src = tmp_path / "leaf.py"
    src.write_text("import numpy\nfrom iceg.features import extract\n", encoding="utf-8")
    found = [m for _, m, _ in _imports(src) if m.split(".")[0] in FORBIDDEN["frontends"]]
    assert found == ["iceg.features"]
