"""The analysis steps of a reconstruction job, and the rig's minimal detectable changes.

Calls ``analysis`` exactly as ``torsoscan indices`` and ``torsoscan compare``
do, and keeps their files and pictures in storage:

- every torso gets its clinical indices, its shaded views (the reconstruction's mesh, with the
  landmarks and the line of symmetry) and asymmetry map;
- every torso is compared with each earlier visit's (a change) and with the
  earlier captures of its own visit (a repeat pair: the rig's repeatability);
- the minimal detectable change of every figure comes from all repeat pairs
  of the clinic's rigs.
"""

import json
import shutil
import tempfile
from pathlib import Path

from django.core.files import File
from django.core.files.storage import default_storage
from django.db import IntegrityError, transaction
from django.db.models import Min

from .models import Camera, Comparison, Reconstruction


def local_copy(field_or_name, dest: Path) -> Path:
    """A stored file (a file field or a storage name) copied to the local path ``dest`` (the analysis reads files)."""
    name = getattr(field_or_name, "name", field_or_name)
    with default_storage.open(name, "rb") as src, open(dest, "wb") as out:
        shutil.copyfileobj(src, out, 1 << 20)
    return dest


def stored(field) -> bool:
    """Whether a file field names a file that storage holds."""
    name = getattr(field, "name", field)
    try:
        return bool(name) and default_storage.exists(name)
    except (OSError, ValueError):
        return False


def _store(folder: str, path: Path) -> str:
    with open(path, "rb") as fh:
        return default_storage.save(f"{folder}/{Path(path).name}", File(fh))


def analyse_reconstruction(rec: Reconstruction) -> Reconstruction:
    """Indices (with the clinician's landmark corrections, if any) and pictures of one torso."""
    from analysis.jsonsafe import clean
    from analysis.pictures import torso_pictures

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # the reconstruction's display mesh, when stored, is what the pictures show (shaded), else the points
        extra = {"mesh_ply": local_copy(rec.mesh, tmp / "torso-mesh.ply")} if stored(rec.mesh) else {}
        out = torso_pictures(local_copy(rec.torso, tmp / "torso.ply"), tmp / "pictures", landmarks=rec.landmarks,
                             **extra)
        folder = f"results/{rec.job.uid}/pictures"
        pictures = {Path(p).stem: _store(folder, Path(p)) for p in out["views"]}
        pictures["asymmetry"] = _store(folder, Path(out["asymmetry"]))
    replaced = [name for name in (rec.pictures or {}).values() if name not in pictures.values()]
    rec.indices = clean(out["indices"])
    rec.pictures = pictures
    rec.save(update_fields=["indices", "pictures"])
    # the old pictures go once the row naming the new ones is committed (a rolled-back save keeps them named)
    transaction.on_commit(lambda: [default_storage.delete(name) for name in replaced])
    return rec


def clinic_mdc(clinic, usable_only: bool = True) -> dict:
    """Minimal detectable change of every figure from the clinic's repeat pairs: figure -> {"mdc", "sem", "n", "ci95"}.

    ``usable_only``: only the figures whose MDC rests on enough repeat pairs
    (:data:`analysis.repeatability.MIN_REPEAT_PAIRS`) to flag anything; one pair never flags. Until the
    clinic's own pairs are enough, an index takes the scanner's repeatability measured on simulated
    re-scans (:func:`analysis.repeatability.scanner_mdc`, ``"source": "scanner"``).
    """
    from analysis.repeatability import mdc_from_comparisons, mdc_from_index_pairs, scanner_mdc, usable_mdc

    pairs = list(Comparison.objects.filter(repeat=True, later__session__rig__clinic=clinic)
                 .select_related("earlier", "later"))
    mdc = mdc_from_comparisons([c.report for c in pairs])
    mdc.update(mdc_from_index_pairs([(c.earlier.indices, c.later.indices) for c in pairs
                                     if c.earlier.indices and c.later.indices]))
    if not usable_only:
        return mdc
    own = {k: {**v, "source": "clinic"} for k, v in usable_mdc(mdc).items()}
    # the scanner's repeatability measured on simulated rigs like the clinic's coarsest (the pairs are pooled)
    width = Camera.objects.filter(rig__clinic=clinic).aggregate(w=Min("width"))["w"]
    return {**scanner_mdc(image_width=width), **own}


def repeat_pairs(clinic) -> int:
    """How many same-visit repeat pairs the clinic's rigs have given (what its noise verdicts rest on)."""
    return Comparison.objects.filter(repeat=True, later__session__rig__clinic=clinic).count()


def compare_reconstructions(earlier: Reconstruction, later: Reconstruction) -> Comparison:
    """Register ``later``'s torso to ``earlier``'s; the report, deformation map and its picture (once per pair)."""
    from analysis.compare import compare_torsos, write_comparison
    from analysis.indices import analysis_from_report
    from analysis.pictures import comparison_pictures
    from analysis.torso import read_torso

    existing = Comparison.objects.filter(earlier=earlier, later=later).first()
    if existing is not None:
        return existing
    read = _as_read(earlier, later)
    mdc = clinic_mdc(later.session.rig.clinic)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # each torso's stored indices (made from its current landmarks, which a correction re-makes before it
        # queues the comparisons again) are its analysis: the comparison shows the numbers of the torsos' own
        # pages and does not analyse them again; a torso without them is analysed here
        result = compare_torsos(read_torso(local_copy(earlier.torso, tmp / "earlier.ply")),
                                read_torso(local_copy(later.torso, tmp / "later.ply")),
                                landmarks=earlier.landmarks or None, later_landmarks=later.landmarks or None,
                                mdc={k: v["mdc"] for k, v in mdc.items()} or None,
                                earlier_analysis=analysis_from_report(earlier.indices),
                                later_analysis=analysis_from_report(later.indices))
        write_comparison(tmp / "out", result)
        report = json.loads((tmp / "out" / "report.json").read_text())
        anm = (mdc.get("average_normal_distance_mm") or {}).get("mdc")
        # the map drawn on the later reconstruction's mesh, in the earlier torso's frame; its arms, neck and head
        # masked by the earlier torso's own indices (frame, vertebra prominens)
        extra = {}
        if stored(later.mesh):
            extra["mesh_ply"] = local_copy(later.mesh, tmp / "later-mesh.ply")
        if earlier.indices:
            extra["indices"] = earlier.indices
        pics = comparison_pictures(tmp / "out", tmp / "pictures", mdc_mm=anm, **extra)
        comparison = Comparison(earlier=earlier, later=later, report=report)
        with open(tmp / "out" / "deformation.ply", "rb") as fh:
            comparison.deformation.save(f"{earlier.pk}-{later.pk}-deformation.ply", File(fh), save=False)
        folder = f"comparisons/{earlier.pk}-{later.pk}"
        comparison.pictures = {Path(p).stem: _store(folder, Path(p)) for p in _paths(pics)}
        try:
            with transaction.atomic():
                # a torso whose landmarks or indices changed meanwhile (a clinician's correction): this result is
                # stale, and the correction's job queues the pair again
                now = {r.pk: r for r in Reconstruction.objects.select_for_update().filter(pk__in=[earlier.pk,
                                                                                                later.pk])}
                if len(now) < 2 or _as_read(now[earlier.pk], now[later.pk]) != read:
                    raise StaleComparison(f"the landmarks of scan {earlier.pk} or {later.pk} were corrected while "
                                          "they were compared; the comparison is made again from them")
                comparison.save()
        except (IntegrityError, StaleComparison) as exc:
            for name in [comparison.deformation.name, *comparison.pictures.values()]:
                default_storage.delete(name)
            if isinstance(exc, StaleComparison):
                raise
            return Comparison.objects.get(earlier=earlier, later=later)  # stored meanwhile by another job
    return comparison


class StaleComparison(Exception):
    """A comparison finished after one of its torsos' landmarks were corrected: not stored."""


def _as_read(earlier: Reconstruction, later: Reconstruction) -> str:
    """What a comparison of the two torsos rests on besides their files: their landmarks and indices."""
    return json.dumps([[r.pk, r.landmarks, r.indices] for r in (earlier, later)], sort_keys=True, default=str)


def _paths(pics) -> list:
    """Every PNG path in what a pictures function returned (a path, a list, or a dict of them)."""
    if isinstance(pics, (str, Path)):
        return [pics] if str(pics).endswith(".png") else []
    if isinstance(pics, dict):
        return [p for v in pics.values() for p in _paths(v)]
    if isinstance(pics, (list, tuple)):
        return [p for v in pics for p in _paths(v)]
    return []
