"""One analysis per distinct torso (or pair of torsos) and landmarks in a test session.

The page tests build the same synthetic visits again and again; analysing a
torso (indices, shaded views, asymmetry map: about 3 s) and comparing two
(registration, deformation: about 4 s) are deterministic, so after the first
time the results are copies of the first one's. A torso whose landmarks a
test corrects is a different key, and is analysed for real.
The analysis itself is tested without this (tests/test_analysis_*.py,
tests/test_pipeline_comparisons.py, the service flows).
"""

import copy
import hashlib
import json
import shutil
import tempfile
from pathlib import Path

_RESULTS: dict = {}
_FOLDER = Path(tempfile.mkdtemp(prefix="torsoscan-analysis-cache-"))


def _key(torso_ply, landmarks) -> str:
    digest = hashlib.sha256(Path(torso_ply).read_bytes())
    digest.update(_json(landmarks))
    return digest.hexdigest()


def _json(value) -> bytes:
    return json.dumps(value, sort_keys=True, default=str).encode()


def reuse_analyses(monkeypatch):
    """Both patches below."""
    reuse_torso_pictures(monkeypatch)
    reuse_comparisons(monkeypatch)


def reuse_comparisons(monkeypatch):
    """Patch ``analysis.compare.compare_torsos`` (what the clinic's comparison step calls) to reuse results."""
    import analysis.compare

    compare = analysis.compare.compare_torsos

    def compare_torsos(earlier, later, **kw):
        digest = hashlib.sha256()
        for torso in (earlier, later):
            digest.update(torso.points.tobytes())
            digest.update(torso.normals.tobytes())
        digest.update(_json(kw))
        key = "compare-" + digest.hexdigest()
        if key not in _RESULTS:
            _RESULTS[key] = compare(earlier, later, **kw)
        return copy.deepcopy(_RESULTS[key])

    monkeypatch.setattr(analysis.compare, "compare_torsos", compare_torsos)


def reuse_torso_pictures(monkeypatch):
    """Patch ``analysis.pictures.torso_pictures`` (what the clinic's analysis step calls) to reuse results."""
    import analysis.pictures

    compute = analysis.pictures.torso_pictures

    def torso_pictures(torso_ply, out_dir, landmarks=None, mesh_ply=None):
        key = _key(torso_ply, landmarks)
        if mesh_ply is not None:  # the pictures are drawn on the mesh: another mesh, other pictures
            key = hashlib.sha256((key + hashlib.sha256(Path(mesh_ply).read_bytes()).hexdigest()).encode()).hexdigest()
        if key not in _RESULTS:
            _RESULTS[key] = compute(torso_ply, _FOLDER / key, landmarks=landmarks, mesh_ply=mesh_ply)
        first = _RESULTS[key]
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)

        def copied(path):
            return shutil.copy2(path, out / Path(path).name)

        return {"views": [copied(p) for p in first["views"]], "asymmetry": copied(first["asymmetry"]),
                "indices": copy.deepcopy(first["indices"])}

    monkeypatch.setattr(analysis.pictures, "torso_pictures", torso_pictures)
