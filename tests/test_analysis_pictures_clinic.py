"""The clinic's analysis step draws the pictures on the reconstruction's mesh (issue 28 §1).

The picture functions are replaced by recorders: what is tested is what the
step hands them, the stored mesh (torso views and asymmetry map: the torso's
own; deformation map: the later torso's) and the earlier torso's indices (the
frame and landmarks the map's views and masks come from).
"""

import json
from pathlib import Path

import pytest

from tests.patient_records import two_torsos

MESH = b"ply mesh of scan %d"
INDICES = {"format": "torso-indices/1", "frame": {"origin_mm": [0, 0, 0], "left": [1, 0, 0], "posterior": [0, 1, 0],
                                                  "up": [0, 0, 1]},
           "landmarks": {"vertebra_prominens": {"position_mm": [0, 60, 1330]}}}


@pytest.fixture
def scans(clinic):
    return two_torsos(clinic, "RIG-M", "P-M", "Mo Mesh", indices=INDICES, mesh=MESH)[1]


def _png(folder, name):
    Path(folder).mkdir(parents=True, exist_ok=True)
    path = Path(folder) / name
    path.write_bytes(b"\x89PNG " + name.encode())
    return str(path)


@pytest.mark.django_db
def test_it_draws_a_torsos_pictures_on_its_stored_mesh(scans, monkeypatch):
    import analysis.pictures
    from clinic.analysis_step import analyse_reconstruction

    seen = {}

    def torso_pictures(torso_ply, out_dir, landmarks=None, mesh_ply=None):
        seen["mesh"] = Path(mesh_ply).read_bytes() if mesh_ply else None
        return {"views": [_png(out_dir, "torso-back.png")], "asymmetry": _png(out_dir, "asymmetry.png"),
                "indices": INDICES}

    monkeypatch.setattr(analysis.pictures, "torso_pictures", torso_pictures)
    rec = analyse_reconstruction(scans[1])
    assert seen["mesh"] == MESH % 1
    assert set(rec.pictures) == {"torso-back", "asymmetry"}


@pytest.mark.django_db
def test_it_draws_a_comparisons_map_on_the_later_mesh_in_the_earlier_frame(scans, monkeypatch):
    import analysis.compare
    import analysis.pictures
    import analysis.torso
    from clinic.analysis_step import compare_reconstructions

    seen = {}

    def write_comparison(out, result):
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "report.json").write_text(json.dumps({"average_normal_distance_mm": 0.4}))
        (Path(out) / "deformation.ply").write_bytes(b"ply deformation")

    def comparison_pictures(out, dest, mdc_mm=None, mesh_ply=None, indices=None):
        seen.update(mesh=Path(mesh_ply).read_bytes() if mesh_ply else None, indices=indices)
        return {"deformation": _png(dest, "deformation.png")}

    monkeypatch.setattr(analysis.torso, "read_torso", lambda path: str(path))
    monkeypatch.setattr(analysis.compare, "compare_torsos", lambda earlier, later, **kw: {})
    monkeypatch.setattr(analysis.compare, "write_comparison", write_comparison)
    monkeypatch.setattr(analysis.pictures, "comparison_pictures", comparison_pictures)
    earlier, later = scans
    comparison = compare_reconstructions(earlier, later)
    assert seen["mesh"] == MESH % 1  # the later torso's surface
    assert seen["indices"] == INDICES  # the earlier torso's frame and vertebra prominens
    assert set(comparison.pictures) == {"deformation"}


@pytest.mark.django_db
def test_it_draws_the_points_when_no_mesh_is_stored(scans, monkeypatch):
    import analysis.pictures
    from clinic.analysis_step import analyse_reconstruction

    seen = {}

    def torso_pictures(torso_ply, out_dir, landmarks=None, **kw):
        seen.update(kw)
        return {"views": [_png(out_dir, "torso-back.png")], "asymmetry": _png(out_dir, "asymmetry.png"),
                "indices": INDICES}

    monkeypatch.setattr(analysis.pictures, "torso_pictures", torso_pictures)
    rec = scans[0]
    rec.mesh = ""
    rec.save()
    analyse_reconstruction(rec)
    assert seen == {}
