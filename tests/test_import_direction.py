"""Imports run one way (issue 29): clinic on analysis on recon_engine, never back.

The engine is plain Python that other tools embed: it imports neither the
analysis nor the clinic service (Django), and the analysis not the clinic.
The scan reads the source (AST), so an import inside a function counts too.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# package -> the project's packages it must not import
FORBIDDEN = {"recon_engine": ("analysis", "clinic"), "analysis": ("clinic",)}


def upward_imports(path: Path, forbidden: tuple) -> list[str]:
    """``import X`` / ``from X import ...`` of a forbidden top-level package in one file (absolute imports:
    a relative import stays inside its own package)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            mods = [node.module or ""]
        else:
            continue
        found += [f"{name}:{node.lineno}: {ast.unparse(node)}" for m in mods if m.split(".")[0] in forbidden]
    return found


def test_the_scan_finds_an_upward_import(tmp_path):
    probe = tmp_path / "m.py"
    probe.write_text("import numpy\nfrom . import bundle\nimport analysis.torso as t\n"
                     "def f():\n    from clinic.models import Job\n")
    found = upward_imports(probe, FORBIDDEN["recon_engine"])
    assert [f.split(": ", 1)[1] for f in found] == ["import analysis.torso as t", "from clinic.models import Job"]


def test_the_engine_imports_neither_analysis_nor_clinic_and_analysis_not_clinic():
    found = [f for package, forbidden in FORBIDDEN.items() for p in sorted((ROOT / package).rglob("*.py"))
             for f in upward_imports(p, forbidden)]
    assert found == []
