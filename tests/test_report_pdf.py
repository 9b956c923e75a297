"""The reports on paper: a PDF of at most two A4 pages per visit and per comparison, read back as text.

The records are made by hand (indices, pictures and the comparison's report as the analysis writes them), so
no engine runs and the tests take seconds. The text is read from the PDF itself: each content stream inflated,
the strings of its text operators joined per text block (matplotlib writes one block per line of text).
"""

import io
import re
import zlib

import pytest
from django.core.files.base import ContentFile
from django.core.files.storage import default_storage


# --- reading a PDF back -----------------------------------------------------------------------------------------------

def _unescape(s: bytes) -> bytes:
    def one(m):
        g = m.group(1)
        if g[:1].isdigit():
            return bytes([int(g, 8) & 0xFF])
        return {b"n": b"\n", b"r": b"\r", b"t": b"\t"}.get(g, g)

    return re.sub(rb"\\([0-7]{1,3}|.)", one, s, flags=re.S)


def pdf_text(data: bytes) -> str:
    """The ASCII text of a matplotlib PDF, one line per text block (symbols outside Latin-1 come out garbled)."""
    lines = []
    for m in re.finditer(rb"stream\r?\n(.*?)endstream", data, re.S):
        raw = m.group(1)
        try:
            raw = zlib.decompress(raw)
        except zlib.error:
            pass
        for block in re.findall(rb"\bBT\b(.*?)\bET\b", raw, re.S):
            strings = re.findall(rb"\(((?:\\.|[^\\)])*)\)", block, re.S)
            lines.append(b"".join(_unescape(s) for s in strings).decode("latin-1"))
    return "\n".join(lines)


def page_count(data: bytes) -> int:
    return len(re.findall(rb"/Type\s*/Page\b", data))


def test_the_reader_finds_text_and_pages_and_misses_what_is_absent():
    # the reader itself can fail: a text that is not there is not found, pages are counted
    from clinic.report import Sheets

    sheets = Sheets("head", "foot")
    sheets.para("Robin (P-88) has a 12.5 mm hump \\ on the right")
    data = sheets.pdf()
    text = pdf_text(data)
    assert "Robin (P-88) has a 12.5 mm hump \\ on the right" in text
    assert "Robin (P-99)" not in text and page_count(data) == 1


def test_a_latin_text_uses_the_viewers_helvetica_and_any_other_an_embedded_font():
    from clinic.report import Sheets

    latin = Sheets("head", "foot")
    latin.para("Zoë Müller-Ødegård, 4.0° ± 0.7° – ok")
    data = latin.pdf()
    assert b"/Helvetica" in data and b"DejaVu" not in data
    assert "Zo\xeb M\xfcller-\xd8deg\xe5rd, 4.0\xb0 \xb1 0.7\xb0" in pdf_text(data)
    # a name the core fonts cannot write is embedded as written, never printed with a "?"
    other = Sheets("head", "foot")
    other.para("\u0141ucja \u017bak \u2192 \u25b2 beyond noise")
    data = other.pdf()
    assert b"DejaVu" in data and b"/Helvetica" not in data
    text = pdf_text(data)
    assert "ucja" in text and "?ucja" not in text and "to beyond noise" in text


def test_what_does_not_fit_on_two_pages_is_left_out_and_said():
    from clinic.report import Sheets

    sheets = Sheets("Robin Report · ID P-88", "Produced by test")
    for k in range(200):
        sheets.para(f"line {k} of a long text that does not fit on two pages")
    data = sheets.pdf()
    text = pdf_text(data)
    assert page_count(data) == 2
    assert "line 0 of" in text and "line 199 of" not in text
    assert "Not everything fitted on two pages" in text
    assert "Robin Report" in text and "page 2 of 2" in text  # the second sheet names the patient too


# --- a patient with two visits, made by hand --------------------------------------------------------------------------

def _png(title, w=3.0, h=3.6):
    import numpy as np
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=50)
    ax = fig.add_subplot()
    img = ax.imshow(np.linspace(-6, 6, 400).reshape(20, 20), cmap="RdBu_r", vmin=-6, vmax=6)
    fig.colorbar(img, label="mm")
    ax.set_title(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def indices(rotation, lateral, length):
    """A ``torso-indices/1`` report as the analysis writes it (the figures the pages and the report read)."""
    def sided(value, level):
        side = {"size": abs(value), "level": level, "height_mm": level * length}
        return {"rms": abs(value) * 0.6, "max": value, "right": side if value > 0 else None,
                "left": side if value < 0 else None}

    return {"format": "torso-indices/1", "lateral_deviation_mm": sided(lateral, 0.45),
            "spine_lateral_deviation_mm": sided(lateral * 1.5, 0.5),
            "surface_rotation_deg": sided(rotation, 0.6), "midline_rotation_deg": sided(rotation * 0.8, 0.62),
            "hump_mm": rotation * 2.5, "hump_angle_deg": rotation, "trunk_imbalance_mm": 3.0,
            "trunk_inclination_mm": -20.0, "asymmetry_mm": 6.0 + rotation / 4, "trunk_length_mm": length,
            # newer indices (where labels.py has them, the tables are longer: the reports must still fit)
            "cobb_estimate_deg": rotation * 1.8, "kyphotic_angle_deg": 42.0, "lordotic_angle_deg": 35.0,
            "pelvic_obliquity_mm": 4.0, "pelvic_torsion_deg": 1.5,
            "frame": {"facing": {"method": "rig", "status": "certain"}},
            "landmarks": {"vertebra_prominens": {"confidence": "high"}, "sacral_point": {"confidence": "high"}}}


@pytest.fixture
def reported_patient(clinic):
    """Robin Report: two visits four months apart, a torso each, and their comparison; ``(patient, visits, comp)``."""
    import datetime

    from clinic.models import CaptureSession, Comparison, Job, Patient, Reconstruction, Rig, Visit

    rig = Rig.objects.create(clinic=clinic, serial="RIG-P", description={})
    patient = Patient.objects.create(clinic=clinic, identifier="P-88", name="Robin Report",
                                     date_of_birth=datetime.date(2013, 3, 14), sex="F")
    visits, recs = [], []
    for k, (date, rotation, lateral, length) in enumerate((("2026-07-01", 4.0, 5.0, 470.0),
                                                            ("2026-11-01", 12.0, 14.0, 478.0))):
        visit = Visit.objects.create(patient=patient, date=date, reason=("baseline", "4-month follow-up")[k])
        session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                                manifest_sha256=str(k), idempotency_key=f"report-{k}",
                                                captured_at=date, state=CaptureSession.FINALIZED)
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED,
                                 percent=100, stage="done")
        pictures = {name: default_storage.save(f"pictures/report-{k}-{name}.png", ContentFile(_png(name)))
                    for name in ("torso-back", "asymmetry")}
        recs.append(Reconstruction.objects.create(job=job, session=session, status="ok", points=1000,
                                                  report={"registration": {"pairs": []}},
                                                  indices=indices(rotation, lateral, length), pictures=pictures))
        visit.refresh_from_db()
        visits.append(visit)
    growth = {"earlier": {"trunk_length_mm": 470.0, "height_mm": 455.0, "width_median_mm": 260.0},
              "later": {"trunk_length_mm": 478.0, "height_mm": 462.0, "width_median_mm": 262.0}}
    growth["change"] = {k: growth["later"][k] - growth["earlier"][k] for k in growth["earlier"]}
    comp = Comparison.objects.create(
        earlier=recs[0], later=recs[1],
        report={"facing": {"consistent": True}, "growth": growth, "average_normal_distance_mm": 0.4,
                "matched_fraction": 0.95, "signed_distance_mm": {"mean": 0.5, "p05": -2.0, "p95": 3.0},
                "regions": {"back_upper": {"mean": 1.2, "p05": -0.5, "p95": 3.0}}},
        pictures={"deformation": default_storage.save("pictures/report-deformation.png",
                                                      ContentFile(_png("deformation", 4, 4)))})
    return patient, visits, comp


# --- the reports ------------------------------------------------------------------------------------------------------

def _get_pdf(client, url):
    r = client.get(url)
    assert r.status_code == 200, r.content[:300]
    assert r["Content-Type"] == "application/pdf" and "no-store" in r["Cache-Control"]
    assert r["Content-Disposition"].startswith("attachment;")
    data = r.content
    assert data.startswith(b"%PDF") and 1 <= page_count(data) <= 2
    text = pdf_text(data)
    assert "Not everything fitted" not in text  # a usual report leaves nothing out
    return text


@pytest.mark.django_db
def test_a_comparison_report_says_what_the_comparison_page_says(client, charlie, reported_patient):
    from clinic import report

    patient, visits, comp = reported_patient
    charlie.first_name, charlie.last_name = "Charlie", "Clinician"
    charlie.save()
    client.force_login(charlie)
    text = _get_pdf(client, f"/comparisons/{comp.pk}/report.pdf")
    for expected in ("Northside Scoliosis Clinic", "Robin Report", "ID P-88", "born 14 Mar 2013",
                     "1 Nov 2026 against 1 Jul 2026 (4 months)", "Between these scans",
                     "Deformation map", "Indices", "Scanner noise (MDC)", "Trend over the visits",
                     "Produced by Charlie Clinician on ", "towards the patient's right", "page 1 of"):
        assert expected in text, expected
    # the verdict is the page's own: every change it lists is on paper, with its words
    h = report.verdict_of(patient.clinic, comp.earlier, comp.later, "Between these scans")
    listed = h["beyond"] + h["unjudged"]
    assert listed, "the two scans differ: the verdict should list changes"
    for item in listed:
        assert item["label"] in text
    assert "Trunk length C7 " in text  # growth, reported apart
    # no internal key on paper
    assert not re.search(r"[a-z]+_[a-z]+_(mm|deg)|\.rms|\.max", text), re.findall(r"\w+_\w+", text)[:5]


@pytest.mark.django_db
def test_a_visit_report_has_the_quality_the_headline_and_the_index_table(client, charlie, reported_patient):
    patient, visits, comp = reported_patient
    client.force_login(charlie)
    text = _get_pdf(client, f"/visits/{visits[1].pk}/report.pdf")
    for expected in ("Robin Report", "ID P-88", "Visit of 1 Nov 2026", "4-month follow-up",
                     "at the visit", "Scan quality: Good scan", "Since the baseline", "Surface indices",
                     "where it is largest", "Sideways deviation of the back's midline, largest",
                     "Rib / lumbar hump height", "Produced by charlie on ", "Trend over the visits"):
        assert expected in text, expected
    # the first visit has nothing before it
    first = _get_pdf(client, f"/visits/{visits[0].pk}/report.pdf")
    assert "Visit of 1 Jul 2026" in first and "this is the patient's first" in first
    assert "Since the baseline" not in first


@pytest.mark.django_db
def test_the_reports_are_for_the_clinics_staff_only(client, nobody, olga, reported_patient):
    patient, visits, comp = reported_patient
    urls = (f"/visits/{visits[1].pk}/report.pdf", f"/comparisons/{comp.pk}/report.pdf")
    for url in urls:
        assert client.get(url).status_code == 302  # to the sign-in page
    for user in (nobody, olga):
        client.force_login(user)
        for url in urls:
            assert client.get(url).status_code == 404, (user, url)


@pytest.mark.django_db
def test_a_report_is_recorded_as_one_download_and_a_refusal_too(client, charlie, olga, reported_patient):
    from clinic.models import AuditEvent

    patient, visits, comp = reported_patient
    url = f"/comparisons/{comp.pk}/report.pdf"
    client.force_login(charlie)
    client.get(url)
    client.force_login(olga)
    client.get(url)
    events = list(AuditEvent.objects.filter(path=url).order_by("pk"))
    assert [(e.action, e.username, e.status, e.patient_id, e.object_type) for e in events] == [
        (AuditEvent.DOWNLOAD, "charlie", 200, patient.pk, "comparison"),
        (AuditEvent.DOWNLOAD, "olga", 404, patient.pk, "comparison")]


@pytest.mark.django_db
def test_the_visit_and_comparison_pages_link_their_report(client, charlie, reported_patient):
    patient, visits, comp = reported_patient
    client.force_login(charlie)
    html = client.get(f"/visits/{visits[1].pk}/").content.decode()
    assert f'href="/visits/{visits[1].pk}/report.pdf"' in html and "Download report (PDF)" in html
    r = client.get(f"/patients/{patient.pk}/compare/?earlier_scan={comp.earlier.pk}&later_scan={comp.later.pk}")
    html = r.content.decode()
    assert f'href="/comparisons/{comp.pk}/report.pdf"' in html and "Download report (PDF)" in html


@pytest.mark.django_db
def test_a_visit_without_a_torso_has_a_one_page_report_and_no_link(client, charlie, reported_patient):
    from clinic.models import Visit

    patient, visits, comp = reported_patient
    empty = Visit.objects.create(patient=patient, date="2026-11-20", reason="brace check")
    client.force_login(charlie)
    assert "Download report (PDF)" not in client.get(f"/visits/{empty.pk}/").content.decode()
    r = client.get(f"/visits/{empty.pk}/report.pdf")
    assert r.status_code == 200 and page_count(r.content) == 1
    text = pdf_text(r.content)
    assert "Visit of 20 Nov 2026" in text and "No scan has been reconstructed for this visit." in text


@pytest.mark.django_db
def test_a_same_day_rescan_report_says_repeatability_not_change(client, charlie, reported_patient):
    from clinic.models import CaptureSession, Comparison, Job, Reconstruction

    patient, visits, comp = reported_patient
    first = comp.later
    session = CaptureSession.objects.create(rig=first.session.rig, kind="torso", visit=visits[1],
                                            manifest={"images": []}, manifest_sha256="r", idempotency_key="report-r",
                                            captured_at="2026-11-01", state=CaptureSession.FINALIZED)
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=session.rig, session=session, state=Job.SUCCEEDED)
    again = Reconstruction.objects.create(job=job, session=session, status="ok", points=1000,
                                          report={"registration": {"pairs": []}},
                                          indices=indices(12.3, 14.2, 478.5), pictures={})
    repeat = Comparison.objects.create(earlier=first, later=again, report={"facing": {"consistent": True}})
    client.force_login(charlie)
    text = _get_pdf(client, f"/comparisons/{repeat.pk}/report.pdf")
    assert "Same-day re-scan of 1 Nov 2026" in text and "repeatability, not a change" in text
    assert "Two scans of the same visit" in text and "Between these scans" not in text
    assert "The deformation map of these two scans has not been drawn." in text
