"""Printing a page in the browser: the print stylesheet leaves the clinical content, without navigation, forms or
the technical details; and (on request) the documentation's pictures of the two PDF reports.

``REPORT_SCREENSHOTS=1`` also writes ``docs/screenshots/report-visit.png`` and ``report-comparison.png`` from a
patient whose torsos and comparison are computed by the analysis (a few minutes), so that the pictures show what
a clinic would print.
"""

import io
import os
from pathlib import Path

import pytest

from tests.test_browser_comparison import CHROMIUM, chromium_or_skip, patient_with_two_visits  # noqa: F401
from tests.test_report_pdf import reported_patient  # noqa: F401 (fixture)

SCREENSHOTS = Path(__file__).resolve().parents[1] / "docs" / "screenshots"


@pytest.mark.django_db(transaction=True)
def test_a_printed_visit_page_shows_the_patient_and_indices_without_navigation_or_forms(live_server, charlie,
                                                                                        reported_patient):
    chromium_or_skip()
    from playwright.sync_api import sync_playwright

    patient, visits, comp = reported_patient
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
        page = browser.new_page(viewport={"width": 1000, "height": 1400})
        page.goto(f"{live_server.url}/accounts/login/")
        page.fill("#id_username", "charlie")
        page.fill("#id_password", "pw-charlie")
        page.click("button[type=submit]")
        page.wait_for_url(f"{live_server.url}/")
        for url in (f"/visits/{visits[1].pk}/",
                    f"/patients/{patient.pk}/compare/?earlier_scan={comp.earlier.pk}&later_scan={comp.later.pk}"):
            page.goto(live_server.url + url)
            on_screen = {s: page.locator(s).first.is_visible() for s in ("header", "details.technical", "form")
                         if page.locator(s).count()}
            assert on_screen and all(on_screen.values()), on_screen  # the check below can fail: they are there
            page.emulate_media(media="print")
            for selector in ("header", "details.technical", "form", ".report-link", ".patient-head .back"):
                loc = page.locator(selector)
                assert all(not loc.nth(k).is_visible() for k in range(loc.count())), (url, selector)
            assert page.locator(".patient-head .name").is_visible()
            assert page.get_by_text("Robin Report").first.is_visible() and page.locator("table").first.is_visible()
            if os.environ.get("REPORT_SCREENSHOTS"):
                page.screenshot(path=f"/tmp/print-{'visit' if 'visits' in url else 'comparison'}.png",
                                full_page=True)
            page.emulate_media(media="screen")
        browser.close()


@pytest.mark.skipif(not os.environ.get("REPORT_SCREENSHOTS"), reason="set REPORT_SCREENSHOTS=1 to write them")
@pytest.mark.django_db
def test_write_the_reports_pictures_for_the_documentation(charlie, patient_with_two_visits):  # noqa: F811
    from django.test import RequestFactory
    from PIL import Image

    from clinic import report
    from clinic.analysis_step import compare_reconstructions
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    p.date_of_birth, p.sex = "2013-03-14", "F"
    p.save()
    recs = list(Reconstruction.objects.filter(session__visit__patient=p).order_by("session__visit__date"))
    comp = compare_reconstructions(recs[0], recs[1])
    request = RequestFactory().get("/")
    request.user = charlie
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    for name, sheets in (("report-comparison.png", report.comparison_sheets(request, comp)),
                         ("report-visit.png", report.visit_sheets(request, recs[1].session.visit))):
        assert not sheets.overflow, name
        # a palette of 96 colours keeps the picture small and the text legible
        Image.open(io.BytesIO(sheets.png(dpi=64))).convert("RGB").quantize(96).save(SCREENSHOTS / name,
                                                                                    optimize=True)
        assert (SCREENSHOTS / name).stat().st_size < 300_000
