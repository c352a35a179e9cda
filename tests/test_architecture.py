"""DESIGN.md boundaries: the robot's package imports nothing from the plant or the ground station."""

import ast
from pathlib import Path

import pytest

ONBOARD = Path(__file__).resolve().parents[1] / "onboard"


def _imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


@pytest.mark.parametrize("path", sorted(ONBOARD.glob("*.py")), ids=lambda p: p.name)
def test_onboard_imports_nothing_from_hil_or_ground(path):
    assert not _imported_roots(path) & {"hil", "ground"}, f"{path.name} imports from hil or ground"


def test_the_check_sees_an_offending_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from ground.commands import arm\n")
    assert "ground" in _imported_roots(bad)
