"""A comparison asked for by a clinician whose idle session had ended: the sign-in keeps the page's address but
not the posted scans, so the page without a pair sends them to the patient's page (where the pair is chosen),
not to a 404."""

from urllib.parse import parse_qs, urlparse

import pytest

from clinic.models import Job
from tests.test_comparison_jobs import quick_analysis, two_scans  # noqa: F401 (fixtures)


@pytest.mark.django_db
def test_it_leads_to_the_patients_page_once_signed_in(client, charlie, two_scans, quick_analysis):  # noqa: F811
    patient, earlier, later = two_scans
    r = client.post(f"/patients/{patient.pk}/compare/", {"earlier_scan": earlier.pk, "later_scan": later.pk})
    assert r.status_code == 302 and "login" in r["Location"]
    after_login = parse_qs(urlparse(r["Location"]).query)["next"][0]
    client.force_login(charlie)
    r = client.get(after_login)
    assert r.status_code == 302 and r["Location"] == f"/patients/{patient.pk}/"
    assert client.get(r["Location"]).status_code == 200
    assert not Job.objects.filter(kind=Job.COMPARISON).exists()  # nothing was started by the lost post
