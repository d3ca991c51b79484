"""The shape of the package: small modules, short functions, imports that follow the flow.

The layering itself (io -> patch -> stereo/psd -> features -> classify -> filter -> map ->
export, cli on top) is checked by import-linter in CI (`lint-imports`, contract in
pyproject.toml); these tests keep the rest of the house rules of the README's "Layout".
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "rough_map"
MODULES = sorted(p for p in PACKAGE.rglob("*.py") if "configs" not in p.parts)


def _name(path: Path) -> str:
    return str(path.relative_to(PACKAGE.parent))


@pytest.mark.parametrize("path", MODULES, ids=_name)
def test_modules_are_small(path: Path) -> None:
    """A bound that catches a module grown out of its concept (issue 31: modules are split
    by concept, and the old 600-line bound had files split off only to meet it)."""
    assert len(path.read_text(encoding="utf-8").splitlines()) <= 1000


@pytest.mark.parametrize("path", MODULES, ids=_name)
def test_functions_are_short(path: Path) -> None:
    """At most 120 lines of code per function, its docstring not counted."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    long = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            lines = (node.end_lineno or node.lineno) - node.lineno + 1
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                doc = body[0]
                lines -= (doc.end_lineno or doc.lineno) - doc.lineno + 1
            if lines > 120:
                long.append(f"{node.name}: {lines} lines")
    assert long == []


def _local_rough_map_imports(tree: ast.AST) -> list[str]:
    found = []
    for func in ast.walk(tree):
        if not isinstance(func, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(func):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rough_map"):
                found.append(f"{func.name}: from {node.module}")
            elif isinstance(node, ast.Import):
                found += [
                    f"{func.name}: {a.name}" for a in node.names if a.name.startswith("rough_map")
                ]
    return found


@pytest.mark.parametrize(
    "path", [p for p in MODULES if "cli" not in p.relative_to(PACKAGE).parts], ids=_name
)
def test_no_function_local_imports_of_rough_map(path: Path) -> None:
    """Only the CLI defers rough_map imports (to keep `rough-map --help` fast); elsewhere a
    function-local import would hide a link against the flow."""
    assert _local_rough_map_imports(ast.parse(path.read_text(encoding="utf-8"))) == []


def test_one_definition_of_each_shared_concept() -> None:
    """One pose, one calibration, one CRS, one patch/extraction spec."""
    defs: dict[str, list[str]] = {}
    for path in MODULES:
        for node in ast.parse(path.read_text(encoding="utf-8")).body:  # module level
            if isinstance(node, ast.ClassDef | ast.FunctionDef):
                defs.setdefault(node.name, []).append(_name(path))
    for name, home in {
        "Pose": "rough_map/config.py",
        "StereoCalibration": "rough_map/config.py",
        "Crs": "rough_map/config.py",
        "PatchSpec": "rough_map/patch/spec.py",
        "Extraction": "rough_map/patch/spec.py",
        "pose_matrix": "rough_map/geometry.py",
        "rotation_matrix": "rough_map/geometry.py",
        "atomic_output": "rough_map/_files.py",
    }.items():
        assert defs.get(name) == [home], (name, defs.get(name))
    assert not any(n in defs for n in ("MapCrs", "_rotation_y", "_pose_matrix"))
