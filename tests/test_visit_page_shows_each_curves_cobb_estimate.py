"""The visit page gives the Cobb-angle estimate of each curve (an S has one on each side, each with its level),
labelled as an estimate from the surface and not a radiograph."""

import pytest

from tests.test_browser_comparison import torso_ply, patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_it_shows_both_curves_of_an_s_as_estimates(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    visit = patient_with_two_visits.visits.order_by("date").first()
    rec = Reconstruction.objects.get(session__visit=visit)
    rec.indices = {**rec.indices, "cobb_estimate_deg": {
        "max": 23.4, "right": {"size": 23.4, "level": 0.64, "height_mm": 290.0},
        "left": {"size": 17.1, "level": 0.29, "height_mm": 130.0}}}
    rec.save(update_fields=["indices"])
    client.force_login(charlie)
    html = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "Cobb angle, estimated from the surface (largest curve)" in html
    assert "An estimate, not a radiograph" in html
    assert ("23.4° curve convex to the patient&#x27;s right at 64 % of the trunk&#x27;s height (290 mm above the "
            "sacral point)") in html
    assert ("17.1° curve convex to the patient&#x27;s left at 29 % of the trunk&#x27;s height (130 mm above the "
            "sacral point)") in html


@pytest.mark.django_db
def test_an_analysed_scan_stores_each_sides_curve(patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    # the later visit's torso (10 deg of rotation at the apex) has curves; the earlier one's line is nearly straight
    rec = (Reconstruction.objects.filter(session__visit__patient=patient_with_two_visits)
           .order_by("session__visit__date").last())
    cobb = rec.indices["cobb_estimate_deg"]
    assert set(cobb) == {"max", "right", "left"}
    curves = rec.indices["cobb_estimate"]["curves"] if rec.indices["cobb_estimate"] else []
    assert curves, "the fixture's curved torso gave no curve: the checks below would check nothing"
    for c in curves:
        assert c["side"] in ("right", "left") and c["value_deg"] > 3.0  # every curve beyond the 3° swing
        assert c["lower_level"] <= c["apex_level"] <= c["upper_level"]
