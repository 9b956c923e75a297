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

def _without_download_time(text):
    """The report's text with the footer's time of download ("at 14:29 UTC") taken out: two downloads of the same
    state may straddle a minute."""
    return re.sub(r" at \d\d:\d\d ", " at HH:MM ", text)


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


# --- drawn once per state, the footer written on each download -----------------------------------------------------

def _footer_position(data: bytes) -> tuple[float, float]:
    """Where the text block that starts "Produced by" begins: the ``x y Td`` before its string."""
    for m in re.finditer(rb"stream\r?\n(.*?)endstream", data, re.S):
        raw = m.group(1)
        try:
            raw = zlib.decompress(raw)
        except zlib.error:
            pass
        for block in re.findall(rb"\bBT\b(.*?)\bET\b", raw, re.S):
            if b"(Produced by" in block:
                x, y = re.search(rb"([-\d.]+) ([-\d.]+) Td", block).groups()
                return float(x), float(y)
    raise AssertionError("no footer")


def _cross_references_hold(data: bytes) -> dict:
    """Every in-use entry of the PDF's (one) cross-reference table points at its object; returns the trailer's
    document information as ``{key: value}`` (literal strings only)."""
    start = int(re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", data).group(1))
    head = re.match(rb"xref\s+0 (\d+)\s+", data[start:])
    size = int(head.group(1))
    entries = re.findall(rb"(\d{10}) (\d{5}) ([nf])", data[start + head.end():])[:size]
    assert len(entries) == size
    for k, (offset, _, kind) in enumerate(entries):
        if kind == b"n":
            assert data[int(offset):].startswith(b"%d 0 obj" % k), k
    trailer = data[start:]
    assert b"/Size %d " % size in trailer and data.count(b"startxref") == 1
    info = int(re.search(rb"/Info (\d+) 0 R", trailer).group(1))
    body = data[int(entries[info][0]):].split(b"endobj", 1)[0]
    return {k.decode(): _unescape(v).decode("latin-1")
            for k, v in re.findall(rb"/(\w+) \(((?:\\.|[^\\)])*)\)", body)}


def _page_texts(data: bytes) -> list[str]:
    """Each page's text: the streams its ``/Contents`` names (one or an array), found through the cross-references."""
    start = int(re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", data).group(1))
    head = re.match(rb"xref\s+0 (\d+)\s+", data[start:])
    offsets = [int(o) for o, _, _ in re.findall(rb"(\d{10}) (\d{5}) ([nf])", data[start + head.end():])]

    def obj(k):
        return data[offsets[k]:].split(b"endobj", 1)[0]

    texts = []
    for page in re.findall(rb"<< /Type /Page\b.*?>>", data, re.S):
        refs = re.search(rb"/Contents (\[[^\]]*\]|\d+ 0 R)", page).group(1)
        texts.append("\n".join(pdf_text(obj(int(k)) + b"endobj") for k in re.findall(rb"(\d+) 0 R", refs)))
    return texts


@pytest.fixture
def draws(monkeypatch):
    """Counts of what costs: the reports laid out, the PDF pages matplotlib draws and the trend pictures drawn; the
    cache emptied first."""
    from django.core.cache import cache
    from matplotlib.backends.backend_pdf import PdfPages

    from analysis import pictures
    from clinic.report import Sheets

    cache.clear()
    counts = {"layouts": 0, "pages": 0, "trends": 0}
    savefig, trend_picture, init = PdfPages.savefig, pictures.trend_picture, Sheets.__init__

    def counted_init(self, *a, **kw):
        counts["layouts"] += 1
        return init(self, *a, **kw)

    def counted_savefig(self, *a, **kw):
        counts["pages"] += 1
        return savefig(self, *a, **kw)

    def counted_trend(*a, **kw):
        counts["trends"] += 1
        return trend_picture(*a, **kw)

    monkeypatch.setattr(PdfPages, "savefig", counted_savefig)
    monkeypatch.setattr(Sheets, "__init__", counted_init)
    monkeypatch.setattr(pictures, "trend_picture", counted_trend)
    return counts


@pytest.mark.django_db
def test_a_second_download_is_served_from_the_cache_with_its_own_footer(client, charlie, ada, olga, nobody,
                                                                        reported_patient, draws):
    patient, visits, comp = reported_patient
    charlie.first_name, charlie.last_name = "Charlie", "Clinician"
    charlie.save()
    for url in (f"/visits/{visits[1].pk}/report.pdf", f"/comparisons/{comp.pk}/report.pdf"):
        client.force_login(charlie)
        before = dict(draws)
        first = client.get(url).content
        assert draws["pages"] - before["pages"] == page_count(first) and draws["trends"] - before["trends"] <= 1
        drawn = dict(draws)
        again = client.get(url).content
        assert draws == drawn  # nothing laid out or drawn: the pages and the trend came from the cache
        # the same text but the footer's clock, which may have passed a minute between the two downloads
        assert _without_clock(pdf_text(again)) == _without_clock(pdf_text(first))
        assert "Produced by Charlie Clinician on " in pdf_text(again)
        assert _cross_references_hold(again)["Author"] == "charlie"
        # another member of the clinic: the same drawing, with her own name in the footer and the metadata
        client.force_login(ada)
        other = client.get(url).content
        assert draws == drawn
        assert "Produced by ada on " in pdf_text(other) and "Charlie" not in pdf_text(other)
        assert _cross_references_hold(other)["Author"] == "ada"
        assert page_count(other) == page_count(first)
        # the cache does not open a report to anyone else: still 404 for another clinic, and no drawing
        for user in (olga, nobody):
            client.force_login(user)
            assert client.get(url).status_code == 404
        assert draws == drawn


def _without_clock(text: str) -> str:
    """A report's text with the footer's time of production (``at 18:56 UTC``) left out."""
    return re.sub(r" at \d{2}:\d{2}\b", " at --:--", text)


def _new_picture(name, label) -> dict:
    """A picture stored again under a name of its own, as analysis_step stores a redrawn one."""
    return {name: default_storage.save(f"pictures/report-1-{name}-2.png", ContentFile(_png(f"{name}, {label}")))}


@pytest.mark.django_db
def test_a_report_is_never_stale_after_a_change_it_shows(client, charlie, reported_patient, draws):
    from clinic.models import Reconstruction

    patient, visits, comp = reported_patient
    client.force_login(charlie)
    url = f"/visits/{visits[1].pk}/report.pdf"
    text = _get_pdf(client, url)
    assert "Notes:" not in text and "Rib / lumbar hump height" in text
    # a note added to the visit
    visits[1].notes = "Brace worn 20 hours a day since August."
    visits[1].save()
    pages = draws["pages"]
    text = _get_pdf(client, url)
    assert "Notes: Brace worn 20 hours a day since August." in text and draws["pages"] > pages
    # a landmark correction: the analysis writes the torso's indices and pictures again (here, by hand)
    rec = Reconstruction.objects.get(pk=comp.later.pk)
    hump = rec.indices["hump_mm"]
    assert f"{hump:.1f} mm" in text
    rec.indices = {**rec.indices, "hump_mm": 41.7,
                   "landmarks": {**rec.indices["landmarks"], "vertebra_prominens": {"confidence": "clinician"}}}
    rec.pictures = {**rec.pictures, **_new_picture("torso-back", "corrected")}
    rec.save()
    pages, trends = draws["pages"], draws["trends"]
    text = _get_pdf(client, url)
    assert "41.7 mm" in text and f"{hump:.1f} mm" not in text
    assert draws["pages"] > pages and draws["trends"] == trends + 1  # the trend shows the new hump too
    # the same state again: from the cache
    pages, trends = draws["pages"], draws["trends"]
    assert _without_download_time(_get_pdf(client, url)) == _without_download_time(text)
    assert (draws["pages"], draws["trends"]) == (pages, trends)
    # a change the report does not show (a job's lease, the next visit due): laid out again, not drawn again
    visits[1].next_visit_due = "2027-03-01"
    visits[1].save()
    layouts = draws["layouts"]
    assert _without_download_time(_get_pdf(client, url)) == _without_download_time(text)
    assert (draws["pages"], draws["trends"]) == (pages, trends)
    assert draws["layouts"] == layouts + 1
    # the asymmetry map alone drawn again: a new drawing of the report
    rec.pictures = {**rec.pictures, **_new_picture("asymmetry", "redrawn")}
    rec.save()
    _get_pdf(client, url)
    assert draws["pages"] > pages and draws["trends"] == trends


@pytest.mark.django_db
def test_a_comparison_run_again_is_reported_as_it_now_stands(client, charlie, reported_patient, draws):
    patient, visits, comp = reported_patient
    client.force_login(charlie)
    url = f"/comparisons/{comp.pk}/report.pdf"
    text = _get_pdf(client, url)
    assert "Trunk height +7.0 mm (455.0 mm to 462.0 mm)" in text  # growth, as the comparison measured it
    comp.report["growth"]["later"]["height_mm"] = 466.5
    comp.report["growth"]["change"]["height_mm"] = 11.5
    comp.save()
    pages = draws["pages"]
    text = _get_pdf(client, url)
    assert "Trunk height +11.5 mm (455.0 mm to 466.5 mm)" in text and "+7.0 mm" not in text
    assert draws["pages"] > pages


def test_the_written_footer_sits_where_matplotlib_draws_it_and_the_file_holds_together():
    import datetime

    from clinic.report import Sheets, stamp

    footer = "Produced by Dr (Ann) O'Hara on 2 Dec 2026 at 09:15 UTC · Northside · torsoscan surface scan report"
    sheets = Sheets("Robin Report · ID P-88", footer)
    for k in range(90):
        sheets.para(f"line {k} of a text on two pages")
    drawn = sheets.pdf()
    written = stamp(sheets.static_pdf(), footer, {"Title": "Visit report, Zoë", "Author": "ann",
                                                   "CreationDate": datetime.datetime.now(datetime.timezone.utc)})
    assert page_count(written) == page_count(drawn) == 2
    (x0, y0), (x1, y1) = _footer_position(drawn), _footer_position(written)
    assert abs(x0 - x1) < 0.05 and abs(y0 - y1) < 0.05, ((x0, y0), (x1, y1))
    assert [footer in t for t in _page_texts(written)] == [True, True] and "page 2 of 2" in pdf_text(written)
    info = _cross_references_hold(written)
    assert info["Author"] == "ann" and info["CreationDate"].startswith("D:20")
    assert "Title" not in info  # not ASCII: written as UTF-16 (hex), not a literal
    assert b"/Title <FEFF" in written


@pytest.mark.django_db
def test_a_footer_the_viewers_font_cannot_write_is_drawn_with_the_report(client, charlie, reported_patient, draws):
    patient, visits, comp = reported_patient
    charlie.first_name, charlie.last_name = "\u0141ucja", "\u017bak"
    charlie.save()
    client.force_login(charlie)
    url = f"/visits/{visits[1].pk}/report.pdf"
    for _ in range(2):
        pages = draws["pages"]
        r = client.get(url)
        assert r.status_code == 200 and draws["pages"] > pages  # drawn in full each time
        text = pdf_text(r.content)
        assert "ucja" in text and "?ucja" not in text and "Produced by" in text


@pytest.mark.django_db
def test_a_report_in_an_embedded_font_gets_the_footer_written_on_too(client, charlie, reported_patient, draws):
    patient, visits, comp = reported_patient
    patient.name = "\u0141ucja \u017bak"
    patient.save()
    client.force_login(charlie)
    url = f"/comparisons/{comp.pk}/report.pdf"
    first = client.get(url).content
    pages = draws["pages"]
    again = client.get(url).content
    assert draws["pages"] == pages  # from the cache
    assert b"DejaVu" in again and b"/Helvetica" in again  # the pages embed their font; the footer is Helvetica's
    assert page_count(again) == page_count(first)
    assert all("Produced by charlie on " in t for t in _page_texts(again))
    assert _cross_references_hold(again)["Author"] == "charlie"
