"""Two people editing the same patient or visit at once: the later save does not silently undo the earlier's
fields; it is refused (409), names what changed meanwhile, keeps the person's entries, and a second save keeps
them knowingly.

Each person's form is read from the page as the browser would submit it (every field and hidden input the page
drew, so a version field a fix adds is posted back too); each changes one field and saves.
"""

from html.parser import HTMLParser

import pytest

from clinic.models import Patient, Visit


class _Form(HTMLParser):
    """The fields of the page's data form (``class="card form"``), as a browser would post them."""

    def __init__(self):
        super().__init__()
        self.data, self._in, self._textarea, self._select = {}, False, None, None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "form" and "form" in (a.get("class") or "").split():
            self._in = True
        if not self._in:
            return
        if tag == "input" and a.get("name") and a.get("type") not in ("submit", "button"):
            if a.get("type") in ("checkbox", "radio") and "checked" not in a:
                return
            self.data[a["name"]] = a.get("value") or ""
        elif tag == "textarea":
            self._textarea = a["name"]
            self.data[self._textarea] = ""
        elif tag == "select":
            self._select = a["name"]
            self.data.setdefault(self._select, "")
        elif tag == "option" and self._select and "selected" in a:
            self.data[self._select] = a.get("value") or ""

    def handle_endtag(self, tag):
        if tag == "form":
            self._in = False
        elif tag == "textarea":
            self._textarea = None
        elif tag == "select":
            self._select = None

    def handle_data(self, data):
        if self._textarea:
            self.data[self._textarea] += data


def form_of(client, url) -> dict:
    r = client.get(url)
    assert r.status_code == 200
    parser = _Form()
    parser.feed(r.content.decode())
    assert parser.data, "no form on the page"
    return parser.data


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
    assert "Someone else saved this record" in html and "next visit due (now 2027-01-01)" in html
    assert "Risser 2, Adams forward bend positive" in html  # the clinician's entry is kept on the form
    # saving the form shown again (its version is the record's now) keeps the clinician's entries knowingly
    again = _Form()
    again.feed(html)
    again.data["next_visit_due"] = "2027-01-01"  # the clinician takes the booked date over
    assert client.post(url, again.data).status_code == 302
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
    assert "date of birth (now 2013-11-20)" in r.content.decode()
