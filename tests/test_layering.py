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


def test_flight_sw_never_reads_ground_truth():
    """DESIGN.md: "Scoring lives in ground_sim, never in flight_sw: flight software never sees ground truth".
    `process` read the pair's truth files and scored itself inside flight_sw; it now reads the pair without them
    and studies.quicklook scores what it wrote. Every pair read in flight_sw leaves the truth out, and nothing
    there touches a pair's ``truth``."""
    offences = []
    for p in sorted((ROOT / "flight_sw").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if isinstance(node, ast.Attribute) and node.attr == "truth":
                offences.append(f"{p.name}:{node.lineno}: .truth")
            # a truth file or pair.json's truth named directly (TRUTH_FILES is used only to keep --out off them)
            named = node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else ""
            if named.startswith("gt_") or named in ("true_frames", "pose_error", "hazards_in_scene_pct"):
                offences.append(f"{p.name}:{node.lineno}: {named!r}")
            if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == "read_pair":
                kw = {k.arg: k.value for k in node.keywords}
                if not (isinstance(kw.get("load_truth"), ast.Constant) and kw["load_truth"].value is False):
                    offences.append(f"{p.name}:{node.lineno}: read_pair without load_truth=False")
    assert not offences, offences


def test_the_flight_side_of_process_runs_on_a_pair_whose_truth_it_cannot_read(tmp_path, capsys):
    """Behind the rule above: flight_sw's `process` without a scorer works on a pair whose truth files are not
    even arrays, writes no score, and its result.json holds nothing of the truth."""
    import argparse
    import json
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from hilkit import small_descent

    from flight_sw.cli import _process

    d = small_descent(tmp_path / "pairs", ["600/300"], px=128).parent / "600_300"
    for f in d.glob("gt_*_i1.npy"):
        f.write_bytes(b"not an array")
    doc = json.loads((d / "pair.json").read_text())  # and pair.json's truth, which it must not read either
    (d / "pair.json").write_text(json.dumps({**doc, "true_frames": "garbage", "pose_error": {"frames": "x"}}))
    args = argparse.Namespace(
        pair_dir=str(d), out=str(tmp_path / "o"), preset="fast", refine_pose=True, deadline=None, sites=None,
        widest_pair=False, aim=None, no_figures=False,
    )  # fmt: skip
    assert _process(args, None) == 0
    assert not (tmp_path / "o" / "score.json").exists() and not (tmp_path / "o" / "confusion.png").exists()
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert "vs_truth" not in doc and "against the truth" not in capsys.readouterr().out
    from protocol.pairdir import TRUTH_META_KEYS, read_pair

    assert not set(TRUTH_META_KEYS) & set(read_pair(d, load_truth=False).meta)
