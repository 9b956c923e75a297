"""Two people editing the same patient or visit at once: the later save does not silently undo the earlier's
fields; it is refused (409), names what changed meanwhile, keeps the person's entries, and a second save keeps
them knowingly.

Each person's form is read from the page as the browser would submit it (every field and hidden input the page
drew, so a version field a fix adds is posted back too); each changes one field and saves.
"""

import pytest
from django import forms

from clinic import views
from clinic.models import Patient, Visit
from tests.page_forms import fields_of, form_of


@pytest.mark.django_db
def test_it_refuses_a_visit_saved_from_a_form_opened_before_another_save(client, charlie, alice, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    v = Visit.objects.create(patient=p, date="2026-07-01", reason="baseline")
    url = f"/visits/{v.pk}/edit"
    client.force_login(charlie)
    charlies = form_of(client, url)  # the clinician opens the visit to write the examination's notes
    client.force_login(alice)
    alices = form_of(client, url)  # meanwhile the technician opens it to book the follow-up

    alices["next_visit_due"] = "2027-01-01"
    assert client.post(url, alices).status_code == 302
    client.force_login(charlie)
    charlies["notes"] = "Risser 2, Adams forward bend positive"
    r = client.post(url, charlies)

    v.refresh_from_db()
    assert r.status_code == 409, r.status_code
    assert (v.notes, str(v.next_visit_due)) == ("", "2027-01-01")  # nothing of the stale form was saved
    html = r.content.decode()
    assert "Someone else saved this record" in html and "Changed meanwhile: next visit due (now 2027-01-01)." in html
    assert "Risser 2, Adams forward bend positive" in html  # the clinician's entry is kept on the form
    # saving the form shown again (its version is the record's now) keeps the clinician's entries knowingly
    again = fields_of(html)
    again["next_visit_due"] = "2027-01-01"  # the clinician takes the booked date over
    assert client.post(url, again).status_code == 302
    v.refresh_from_db()
    assert (v.notes, str(v.next_visit_due)) == ("Risser 2, Adams forward bend positive", "2027-01-01")


@pytest.mark.django_db
def test_it_refuses_a_patient_saved_from_a_form_opened_before_another_save(client, charlie, ada, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    url = f"/patients/{p.pk}/edit"
    client.force_login(ada)
    adas = form_of(client, url)  # the administrator corrects the date of birth from the referral letter
    client.force_login(charlie)
    charlies = form_of(client, url)  # the clinician adds a note

    adas["date_of_birth"] = "2013-11-20"
    assert client.post(url, adas).status_code == 302
    charlies["notes"] = "Brace since 2026-03"
    r = client.post(url, charlies)

    p.refresh_from_db()
    assert r.status_code == 409 and (p.notes, str(p.date_of_birth)) == ("", "2013-11-20"), r.status_code
    assert "Changed meanwhile: date of birth (now 2013-11-20)." in r.content.decode()


@pytest.mark.django_db
def test_a_double_click_on_save_of_an_edit_form_is_not_refused_as_someone_elses_save(client, charlie, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    v = Visit.objects.create(patient=p, date="2026-07-01", reason="baseline")
    url = f"/visits/{v.pk}/edit"
    client.force_login(charlie)
    body = form_of(client, url)
    body["notes"] = "Risser 2, Adams forward bend positive"
    first = client.post(url, body)
    second = client.post(url, body)  # the same form posted again (double click): the browser shows this answer
    v.refresh_from_db()
    assert first.status_code == 302 and v.notes == "Risser 2, Adams forward bend positive"
    assert second.status_code == 302, (
        f"answer {second.status_code}: the clinician's own double click is told 'Someone else saved this record "
        f"... nothing was saved' though nobody else did and the notes were saved")


@pytest.mark.django_db
def test_the_form_shown_again_after_an_identifier_race_keeps_its_version(client, charlie, ada, clinic, monkeypatch):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    Patient.objects.create(clinic=clinic, identifier="P-2", name="Sam")  # saved by another request just after ...
    url = f"/patients/{p.pk}/edit"
    client.force_login(charlie)
    charlies = form_of(client, url)
    assert "based_on" in charlies
    # ... this request's identifier check, which saw no P-2: the save hits the unique constraint
    monkeypatch.setattr(views.PatientForm, "clean", forms.ModelForm.clean)
    charlies.update(identifier="P-2", notes="Brace since 2026-03")
    r = client.post(url, charlies)
    monkeypatch.undo()
    assert r.status_code == 400
    shown = fields_of(r.content.decode())

    client.force_login(ada)  # meanwhile the administrator corrects the date of birth
    adas = form_of(client, url)
    adas["date_of_birth"] = "2013-11-20"
    assert client.post(url, adas).status_code == 302

    client.force_login(charlie)  # the clinician fixes the identifier on the form shown again and saves
    shown["identifier"] = "P-3"
    r = client.post(url, shown)
    p.refresh_from_db()
    assert "based_on" in shown and r.status_code == 409, (
        f"the 400 page drew no version (fields {sorted(shown)}); the save answered {r.status_code} and the "
        f"administrator's date of birth is now {p.date_of_birth}: lost")
