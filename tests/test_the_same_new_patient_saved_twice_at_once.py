"""Two posts of a new patient with the same identifier at once (two people, or two workers): the one that loses
the race is told the identifier is taken (400), not a server error (500).

The form's uniqueness checks and the insert are separate queries: both requests can pass the check, and the
database's ``patient_identifier_per_clinic`` constraint refuses the second insert. The interleaving is made
deterministic here: the other request's insert is committed right after this request's check.
"""

import pytest

from clinic import views
from clinic.models import Patient


@pytest.mark.django_db(transaction=True)
def test_it_says_the_identifier_is_taken(client, charlie, clinic, monkeypatch):
    checked = views.PatientForm.validate_unique

    def the_other_request_commits_after_the_check(form):
        checked(form)  # this request's checks passed: no P-7 yet
        Patient.objects.create(clinic=clinic, identifier="P-7", name="Sam")  # the other request's save, committed

    monkeypatch.setattr(views.PatientForm, "validate_unique", the_other_request_commits_after_the_check)
    client.force_login(charlie)
    client.raise_request_exception = False
    r = client.post("/patients/new", {"clinic": clinic.pk, "identifier": "P-7", "name": "Sam"})

    assert r.status_code == 400, r.status_code
    assert "identifier P-7: the clinic already has a patient with it" in r.content.decode()
    assert Patient.objects.filter(clinic=clinic, identifier="P-7").count() == 1
