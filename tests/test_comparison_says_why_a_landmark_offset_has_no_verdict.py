"""A comparison whose sacral point was marked on one scan only gives the trunk's offsets no verdict, and says why."""

import pytest

from tests.test_browser_comparison import torso_ply, patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_it_says_why_the_trunk_offsets_have_no_verdict(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    first, second = p.visits.order_by("date")
    later = Reconstruction.objects.get(session__visit=second)
    indices = dict(later.indices)
    indices["landmarks"] = {**indices["landmarks"],
                            "sacral_point": {**indices["landmarks"]["sacral_point"], "source": "clinician"}}
    later.indices = indices
    later.save(update_fields=["indices"])
    client.force_login(charlie)
    r = client.post(f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}", follow=True)
    assert r.status_code == 200
    html = r.content.decode()
    assert "no verdict: the sacral point was marked on one scan and found automatically on the other" in html
