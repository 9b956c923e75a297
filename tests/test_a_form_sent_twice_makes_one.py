"""A form posted twice (a double click on Save, a browser re-posting after a slow answer, a reload of the
answer) makes what the person meant once, not twice.

The form is read from the page as the browser would submit it (every hidden input the page drew, so a one-time
token a fix adds is posted back too), then posted twice with the same body.
"""

import pytest

from clinic.models import Patient, Visit
from tests.page_forms import form_of


@pytest.mark.django_db
def test_a_double_click_on_save_makes_one_visit(client, charlie, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    url = f"/patients/{p.pk}/visits/new"
    client.force_login(charlie)
    body = form_of(client, url)
    body.update(date="2026-07-01", reason="follow-up", notes="Risser 2")

    first = client.post(url, body)
    second = client.post(url, body)  # the same form, posted again

    assert first.status_code == 302 and second.status_code == 302 and second["Location"] == first["Location"]
    visits = list(Visit.objects.filter(patient=p).values_list("pk", "date", "reason"))
    assert len(visits) == 1, (f"one form posted twice made {len(visits)} visits {visits} (second answer "
                              f"{second.status_code} {second.get('Location')}): the rig may upload into either, "
                              f"the history shows an empty visit and the worklist lists the patient twice")


@pytest.mark.django_db
def test_a_double_click_on_issue_a_new_key_makes_one_key(client, ada, small_rig):
    rig, _ = small_rig
    page = f"/rigs/{rig.serial}/"
    client.force_login(ada)
    body = form_of(client, page, action=f"/rigs/{rig.serial}/keys")
    live_before = rig.keys.filter(revoked__isnull=True).count()

    client.post(f"/rigs/{rig.serial}/keys", body)  # the browser drops this answer: its key is never seen
    second = client.post(f"/rigs/{rig.serial}/keys", body)  # the answer shown (or a reload of the answer)

    made = rig.keys.filter(revoked__isnull=True).count() - live_before
    live = rig.keys.filter(revoked__isnull=True).order_by("-pk").first()
    html = second.content.decode()
    assert second.status_code == 200 and live.prefix in html  # the key shown is the live one
    assert 'id="replaced-key"' in html and "was revoked: use this one" in html  # and it says the first went
    assert made == 1, (f"one click meant one key; {made} live keys were made and the page (answer "
                       f"{second.status_code}) showed only the last: the others are live credentials nobody "
                       f"holds, listed beside the real one by prefix only")


@pytest.mark.django_db
def test_a_new_patient_form_that_had_errors_can_be_sent_again_and_makes_one(client, charlie, clinic):
    client.force_login(charlie)
    body = form_of(client, "/patients/new")
    body.update(identifier="P-9", name="")  # the name forgotten: the form comes back with its error
    assert client.post("/patients/new", body).status_code == 400
    body["name"] = "Sam"
    first, second = client.post("/patients/new", body), client.post("/patients/new", body)
    assert first.status_code == second.status_code == 302 and first["Location"] == second["Location"]
    assert Patient.objects.filter(identifier="P-9").count() == 1
    # another form (another token) is another patient: the identifier's own check answers
    again = form_of(client, "/patients/new")
    again.update(identifier="P-9", name="Sam")
    r = client.post("/patients/new", again)
    assert r.status_code == 400 and "already has a patient with the identifier P-9" in r.content.decode()
