"""The headline of a comparison whose sacral point was marked on one scan only lists the trunk's offsets under
their own heading, with the reason, on the page and on paper (they were listed as changes "without a noise
estimate yet", which is not why they have no verdict)."""

import pytest

from tests.test_report_pdf import pdf_text, reported_patient  # noqa: F401 (fixture)

HEADING = "No verdict: a landmark was placed two ways"
REASON = "the sacral point was marked on one scan and found automatically on the other; mark it on both"


def _mark_sp_on_the_later_scan(comp):
    later = comp.later
    indices = dict(later.indices)
    indices["landmarks"] = {**indices["landmarks"], "sacral_point": {"confidence": "high", "source": "clinician"}}
    indices["landmarks"]["vertebra_prominens"] = {**indices["landmarks"]["vertebra_prominens"], "source": "auto"}
    earlier = comp.earlier
    e = dict(earlier.indices)
    e["landmarks"] = {k: {**v, "source": "auto"} for k, v in e["landmarks"].items()}
    earlier.indices = e
    earlier.save(update_fields=["indices"])
    later.indices = indices
    later.save(update_fields=["indices"])


@pytest.mark.django_db
def test_the_headline_lists_them_apart_with_the_reason(client, charlie, reported_patient):  # noqa: F811
    from clinic import report

    patient, visits, comp = reported_patient
    _mark_sp_on_the_later_scan(comp)
    h = report.verdict_of(patient.clinic, comp.earlier, comp.later, "Between these scans")
    labels = [c["label"] for c in h["no_verdict"]]
    assert any("imbalance" in x for x in labels) and any("inclination" in x for x in labels)
    assert not any("imbalance" in c["label"] for c in h["unjudged"] + h["within"] + h["beyond"])
    client.force_login(charlie)
    r = client.get(f"/patients/{patient.pk}/compare/?earlier={visits[0].pk}&later={visits[1].pk}")
    html = r.content.decode().replace("&#x27;", "'")
    assert HEADING in html and REASON[0].upper() + REASON[1:] in html
    r = client.get(f"/comparisons/{comp.pk}/report.pdf")
    assert r.status_code == 200
    text = pdf_text(r.content)
    assert HEADING in text and "mark it on both" in text
