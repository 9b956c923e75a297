"""The comparison step of a reconstruction job: the later torso against an earlier visit's.

Calls the analysis (``analysis.compare``) exactly as ``torsoscan compare``
does and keeps its files (``report.json``, ``deformation.ply``) in storage.
"""

import tempfile
from pathlib import Path

from django.core.files import File
from django.core.files.storage import default_storage

from .models import Comparison


def _local(field, dest: Path) -> Path:
    with default_storage.open(field.name, "rb") as src:
        dest.write_bytes(src.read())
    return dest


def compare_reconstructions(earlier, later) -> Comparison:
    """Register ``later``'s torso to ``earlier``'s and record the deformation (idempotent per pair)."""
    from analysis.compare import compare_torsos, write_comparison
    from analysis.torso import read_torso

    existing = Comparison.objects.filter(earlier=earlier, later=later).first()
    if existing is not None:
        return existing
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        result = compare_torsos(read_torso(_local(earlier.torso, tmp / "earlier.ply")),
                                read_torso(_local(later.torso, tmp / "later.ply")))
        write_comparison(tmp / "out", result)
        import json

        report = json.loads((tmp / "out" / "report.json").read_text())
        comparison = Comparison(earlier=earlier, later=later, report=report)
        with open(tmp / "out" / "deformation.ply", "rb") as fh:
            comparison.deformation.save(f"{earlier.pk}-{later.pk}-deformation.ply", File(fh), save=False)
        comparison.save()
    return comparison
