"""The packages import one another only as docs/design.md's table allows ("Packages and who may import whom").

The table had said ``ground_sim`` and ``flight_sw`` import only ``protocol`` while both drew with ``reports``:
nothing checked it. ``ground_sim`` and ``flight_sw`` never import each other (the flight software never sees
ground truth), and nothing imports ``studies``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OURS = {"protocol", "reports", "ground_sim", "flight_sw", "hil_server", "studies"}
MAY_IMPORT = {
    "protocol": {"protocol"},
    "reports": {"reports"},
    "ground_sim": {"ground_sim", "protocol", "reports"},
    "flight_sw": {"flight_sw", "protocol", "reports"},
    "hil_server": {"hil_server", "protocol", "ground_sim", "flight_sw", "reports"},
    "studies": OURS,
}


def imported(path: Path) -> set[str]:
    """Our top-level packages a module imports, at any depth (function-level imports count too)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names & OURS


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_a_package_imports_only_what_the_design_allows(package):
    wrong = {
        str(p.relative_to(ROOT)): sorted(imported(p) - MAY_IMPORT[package])
        for p in sorted((ROOT / package).rglob("*.py"))
        if imported(p) - MAY_IMPORT[package]
    }
    assert not wrong, wrong


def test_the_design_table_says_the_same():
    table = (ROOT / "docs" / "design.md").read_text()
    for package, allowed in MAY_IMPORT.items():
        row = next(line for line in table.splitlines() if line.startswith(f"| `{package}` |"))
        said = set(row.split("|")[3].replace("`", "").replace(",", " ").split()) & OURS
        if package != "studies":  # its row says "everything"
            assert said == allowed - {package}, (package, said)
