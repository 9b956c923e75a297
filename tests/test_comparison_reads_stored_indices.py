"""A comparison rests on each torso's stored indices: the numbers of the torsos' own pages, without a second analysis
of either torso (two thirds of a comparison's time)."""

import json

import numpy as np
import pytest

import analysis.compare
from analysis.compare import compare_torsos
from analysis.indices import analyse_torso, analysis_from_report
from analysis.jsonsafe import clean
from analysis.synthetic import synthetic_back
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401

REAL_COMPARE = compare_torsos


def _stored(torso):
    """What the clinic stores of a torso's analysis, read back: the report through JSON."""
    return json.loads(json.dumps(clean(analyse_torso(torso).report)))


def test_a_comparison_from_stored_reports_equals_one_that_analyses_both_torsos():
    a, _ = synthetic_back(rotation_deg=5, lateral_mm=5, spacing_mm=8.0, noise_mm=0.05, seed=0)
    b, _ = synthetic_back(rotation_deg=10, lateral_mm=10, spacing_mm=8.0, noise_mm=0.05, seed=1)
    mdc = {"surface_rotation_deg": 1.0, "average_normal_distance_mm": 0.2, "trunk_length_mm": 3.0}
    fresh = compare_torsos(a, b, mdc=mdc)
    reread = compare_torsos(a, b, mdc=mdc, earlier_analysis=analysis_from_report(_stored(a)),
                            later_analysis=analysis_from_report(_stored(b)))
    assert "growth" in fresh["report"] and "indices" in fresh["report"]
    # how the rigid registration ended: converged, or stopped in a cycle of that many iterations (never both)
    reg = fresh["report"]["registration"]
    assert isinstance(reg["cycle"], int) and reg["cycle"] >= 0 and not (reg["converged"] and reg["cycle"])
    assert json.dumps(clean(reread["report"]), sort_keys=True) == json.dumps(clean(fresh["report"]), sort_keys=True)
    np.testing.assert_array_equal(reread["deformation_mm"], fresh["deformation_mm"])
    assert all(np.array_equal(reread["regions"][k], fresh["regions"][k]) for k in fresh["regions"])


def test_it_reads_no_analysis_from_a_report_without_its_frame_or_trunk_landmarks():
    assert analysis_from_report(None) is None and analysis_from_report({}) is None
    report = {"format": "torso-indices/1", "frame": {"origin_mm": [0, 0, 0], "left": [1, 0, 0],
                                                     "posterior": [0, 1, 0], "up": [0, 0, 1]},
              "landmarks": {"vertebra_prominens": {"position_mm": [0, 0, 500]}}}
    assert analysis_from_report(report) is None  # no sacral point's entry
    report["landmarks"]["sacral_point"] = {"position_mm": None}  # asked for, not found: NaN, as analysed
    read = analysis_from_report(report)
    assert read is not None and np.isnan(read.landmarks["sacral_point"]).all()
    assert analysis_from_report({**report, "format": "torso-indices/0"}) is None


@pytest.mark.django_db
def test_the_clinic_compares_two_analysed_torsos_without_analysing_them_again(patient_with_two_visits,  # noqa: F811
                                                                              monkeypatch):
    from clinic.analysis_step import compare_reconstructions
    from clinic.models import Reconstruction

    monkeypatch.setattr(analysis.compare, "compare_torsos", REAL_COMPARE)  # not the tests' cache of results

    def analysed_again(*args, **kwargs):
        raise AssertionError("a stored torso was analysed again")

    monkeypatch.setattr(analysis.compare, "analyse_torso", analysed_again)
    earlier, later = Reconstruction.objects.filter(session__visit__patient=patient_with_two_visits).order_by(
        "session__visit__date")
    comparison = compare_reconstructions(earlier, later)
    indices = comparison.report["indices"]
    assert indices["later"]["surface_rotation_deg"] == later.indices["surface_rotation_deg"]
    assert indices["earlier"]["surface_rotation_deg"] == earlier.indices["surface_rotation_deg"]
    assert comparison.report["growth"]["later"]["trunk_length_mm"] == pytest.approx(
        np.linalg.norm(np.subtract(later.indices["landmarks"]["vertebra_prominens"]["position_mm"],
                                   later.indices["landmarks"]["sacral_point"]["position_mm"])))
