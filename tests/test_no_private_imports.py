"""No module uses another module's private names (issue 29): what is shared is public, and named so."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OURS = ("recon_engine", "analysis", "clinic", "benchmarks", "tests")
LOCAL = {p.stem for d in ("benchmarks", "tests") for p in (ROOT / d).glob("*.py")}  # imported by bare name


def _ours(module: str | None, level: int) -> bool:
    return level > 0 or (module or "").split(".")[0] in OURS + tuple(LOCAL)


def private_uses(path: Path) -> list[str]:
    """``from X import _n`` and ``X._n`` where X is one of this project's modules."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    found, modules = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and _ours(node.module, node.level):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.append(f"{name}:{node.lineno}: from {node.module} import {a.name}")
                else:
                    modules.add(a.asname or a.name)  # may be a module (from . import bundle)
        elif isinstance(node, ast.Import):
            modules |= {a.asname or a.name.split(".")[0] for a in node.names if _ours(a.name, 0)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in modules:
                found.append(f"{name}:{node.lineno}: {ast.unparse(node)}")
    return found


def test_the_scan_finds_a_private_import(tmp_path):
    probe = tmp_path / "m.py"
    probe.write_text("from recon_engine.bundle import _x\nfrom recon_engine import bundle\nimport numpy as np\n"
                     "bundle._y\nnp._z\nfrom numpy import _w\n")
    found = private_uses(probe)
    assert [f.split(": ", 1)[1] for f in found] == ["from recon_engine.bundle import _x", "bundle._y"]


def test_no_module_imports_anothers_private_names():
    files = [p for d in OURS for p in (ROOT / d).rglob("*.py")]
    assert [f for p in files for f in private_uses(p)] == []
