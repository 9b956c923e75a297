"""An S curve has a curve on each side: a comparison shows both sides' changes, the larger curve first, so that
"largest" reads the same number on the comparison as on the visit page (it showed only the side that changed
most: 7.2° on the left while the visit page read 10.4° on the right)."""

import pytest

from tests.test_browser_comparison import torso_ply, patient_with_two_visits  # noqa: F401 (fixture)

RIGHT = "right side of the back turned backwards"
LEFT = "left side of the back turned backwards"


def _s_curve(indices, right, left):
    out = dict(indices)
    out["surface_rotation_deg"] = {**out["surface_rotation_deg"], "max": right,
                                   "right": {"size": right, "level": 0.65, "height_mm": 320.0},
                                   "left": {"size": left, "level": 0.25, "height_mm": 120.0}}
    return out


def test_index_changes_keep_each_sides_change_larger_curve_first():
    from analysis.repeatability import index_changes

    base = {"surface_rotation_deg": {"rms": 5.0}}
    c = index_changes(_s_curve(base, 10.4, 7.2), _s_curve(base, 10.5, 7.6),
                      {"surface_rotation_deg.max": {"mdc": 1.1}})["surface_rotation_deg.max"]
    # the verdict rests on the side that changed most, as before
    assert (c["earlier"], c["later"]) == pytest.approx((-7.2, -7.6))
    assert [s["side"] for s in c["sides"]] == ["right", "left"]
    assert c["sides"][0]["earlier"] == pytest.approx(10.4) and c["sides"][0]["later"] == pytest.approx(10.5)
    assert c["sides"][1]["change"] == pytest.approx(-0.4) and c["sides"][1]["exceeds_mdc"] is False


@pytest.mark.django_db
def test_the_comparison_page_names_both_curves(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    first, second = p.visits.order_by("date")
    for visit, (right, left) in ((first, (10.4, 7.2)), (second, (10.5, 7.6))):
        rec = Reconstruction.objects.get(session__visit=visit)
        rec.indices = _s_curve(rec.indices, right, left)
        rec.save(update_fields=["indices"])
    client.force_login(charlie)
    r = client.post(f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}", follow=True)
    assert r.status_code == 200
    html = r.content.decode()
    # the table: both curves in each scan's column, the larger first
    assert f"<td>10.4° {RIGHT}; 7.2° {LEFT}</td><td>10.5° {RIGHT}; 7.6° {LEFT}</td>" in html
    # the verdict: each side's change
    assert "Trunk rotation, largest (patient&#x27;s right: 0.1° larger; patient&#x27;s left: 0.4° larger" in html


def test_a_change_that_rounds_to_nothing_reads_unchanged():
    from clinic import labels

    assert labels.change_words("surface_rotation_deg.max", 10.44, 10.46) == "unchanged"
    assert labels.change_words("surface_rotation_deg.max", 10.4, 10.6) == "0.2° larger"
