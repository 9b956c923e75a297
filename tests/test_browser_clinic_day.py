"""A clinician's day in a real browser, at a desktop's width (1280 px) and a phone's (390 px): sign in, find
today's patient on the worklist, open the history and read the headline, compare the same-day re-scan and the
follow-up, place a landmark by clicking on the back picture, download the visit's report; axe-core on every page (no serious violation).

Playwright on the machine's Chromium, as tests/test_browser_comparison.py. Screenshots of every step at both
widths go to docs/screenshots/clinic-day/ with SAVE_SCREENSHOTS=1, the folder docs/accessibility.md names (none
otherwise: full-page screenshots cost seconds each).
"""

import datetime
import os
import time
from pathlib import Path

import pytest
from django.core.files.base import ContentFile

from tests.test_accessibility import SERIOUS, axe_violations
from tests.test_browser_comparison import (CHROMIUM, chromium_or_skip, patient_with_two_visits,  # noqa: F401
                                           torso_ply)

SHOTS = Path(__file__).resolve().parent.parent / "docs" / "screenshots" / "clinic-day"


@pytest.fixture
def patient_seen_today(patient_with_two_visits):  # noqa: F811
    """The patient of tests/test_browser_comparison.py with a third visit today: a scan and a same-day re-scan."""
    from clinic.analysis_step import analyse_reconstruction
    from clinic.models import CaptureSession, Job, Reconstruction, Rig, Visit

    from django.utils import timezone

    # The worklist is read about a minute after the visit is made: a run that crossed midnight in between found no
    # patient "today" (seen once, at 23:59:05). Close to midnight the test waits for the new day instead.
    now = timezone.localtime()
    to_midnight = (datetime.datetime.combine(now.date() + datetime.timedelta(days=1), datetime.time(),
                                             tzinfo=now.tzinfo) - now).total_seconds()
    if to_midnight < 180:
        time.sleep(to_midnight + 1)
    p = patient_with_two_visits
    rig = Rig.objects.get(serial="RIG-B")
    today = timezone.localdate()  # the server's day (TIME_ZONE), not the machine's
    visit = Visit.objects.create(patient=p, date=today, reason="follow-up")
    for k, seed in enumerate((5, 6)):
        session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                                manifest_sha256=f"today-{k}", idempotency_key=f"today-{k}",
                                                captured_at=today, state=CaptureSession.FINALIZED)
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED,
                                 percent=100, stage="done")
        rec = Reconstruction(job=job, session=session, status="ok", points=1, report={"registration": {"pairs": []}})
        rec.torso.save("torso.ply", ContentFile(torso_ply(14.0, seed)), save=False)
        rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
        rec.save()
        analyse_reconstruction(rec)
    return p, visit


def _pixel_above_sacral_point(rec, mm: float):
    """Where, on ``rec``'s back picture (drawn at its natural size), the skin ``mm`` above the automatic sacral
    point is."""
    import tempfile

    import numpy as np

    from analysis.frame import PatientFrame
    from analysis.pictures import render_view
    from clinic.analysis_step import local_copy
    frame = PatientFrame.from_dict(rec.indices["frame"])
    with tempfile.TemporaryDirectory() as tmp:
        r = render_view(local_copy(rec.torso, Path(tmp) / "torso.ply"), frame, "back")
    target = np.asarray(rec.indices["landmarks"]["sacral_point"]["position_mm"], float) + mm * frame.R[2]
    (x, y), = r.placement.project(target)[0]
    return float(x), float(y)


@pytest.mark.django_db(transaction=True)
def test_a_clinician_goes_through_the_clinic_day_at_both_widths(live_server, patient_seen_today):
    chromium_or_skip()
    from playwright.sync_api import sync_playwright

    from clinic.models import Reconstruction

    p, today = patient_seen_today
    base = live_server.url
    # where to click on each of today's back pictures (the ORM is not for Playwright's event loop)
    click_at = {rec.pk: _pixel_above_sacral_point(rec, 15.0)
                for rec in Reconstruction.objects.filter(session__visit=today)}
    serious = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
        for width in (1280, 390):
            out = SHOTS / str(width) if os.environ.get("SAVE_SCREENSHOTS") else None  # full-page shots cost seconds
            if out is not None:
                out.mkdir(parents=True, exist_ok=True)
            page = browser.new_page(viewport={"width": width, "height": 900}, bypass_csp=True, accept_downloads=True)

            def step(name):
                page.wait_for_load_state("load")
                scroll, inner = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
                assert scroll <= inner, f"{name} scrolls sideways at {width} px"
                serious.extend(f"{v['id']} on {name} at {width} px: {v['targets']}" for v in axe_violations(page)
                               if v["impact"] in SERIOUS)
                if out is not None:
                    page.screenshot(path=str(out / f"{name}.png"), full_page=True)

            page.goto(f"{base}/accounts/login/")
            step("01-sign-in")
            page.fill("#id_username", "charlie")
            page.fill("#id_password", "pw-charlie")
            page.click("button[type=submit]")
            page.wait_for_url(f"{base}/")
            step("02-worklist")
            # today's patient, from the worklist
            # the click returns once the URL has changed, before the new document is read (CI once found the
            # visit's URL with an empty page): wait for the navigation to load
            with page.expect_navigation():
                page.locator("#worklist-today").get_by_role("link", name=p.name).click()
            assert page.url.endswith(f"/visits/{today.pk}/") and p.identifier in page.content()
            step("03-todays-visit")
            page.goto(f"{base}/patients/{p.pk}/")
            headline = page.locator("#headline + *").first.inner_text()
            assert headline.strip(), "the history opens without a headline"
            step("04-history")
            # the same-day re-scan, from the visit page
            page.goto(f"{base}/visits/{today.pk}/")
            with page.expect_navigation(timeout=300_000):
                page.get_by_role("button", name="Compare this visit's 2 scans").click(timeout=300_000)
            page.wait_for_selector("#deformation", timeout=300_000)
            assert "re-scan" in page.locator("h1").first.inner_text().lower()
            step("05-same-day-rescan")
            # the follow-up against the baseline, from the history's form
            page.goto(f"{base}/patients/{p.pk}/")
            scans = page.locator("select[name=earlier_scan] option")
            page.select_option("select[name=earlier_scan]", scans.first.get_attribute("value"))
            page.select_option("select[name=later_scan]", scans.last.get_attribute("value"))
            with page.expect_navigation(timeout=300_000):
                page.locator("form.compare button[type=submit]").click(timeout=300_000)
            page.wait_for_selector("#deformation", timeout=300_000)
            step("06-follow-up-against-baseline")
            # a landmark corrected on today's visit by clicking on the back picture, 15 mm above the automatic one
            page.goto(f"{base}/visits/{today.pk}/")
            picture = page.locator("#pick input[name=at]")
            x, y = click_at[int(picture.get_attribute("src").split("/reconstruction/")[1].split("/")[0])]
            page.check("#pick input[value=sacral_point]")
            with page.expect_navigation(timeout=300_000):
                # the click waits for the navigation it starts: the landmark job runs in the request (embedded
                # default), so give it the navigation's time, not the click's default 30 s
                picture.click(position={"x": x, "y": y}, timeout=300_000)
            assert "Undo the last correction" in page.content() and "was undone" not in page.content()
            step("07-landmark-placed-on-the-picture")
            # the visit's report, downloaded
            with page.expect_download() as download:
                page.get_by_role("link", name="Download report (PDF)").click()
            pdf = Path(download.value.path()).read_bytes()
            assert pdf.startswith(b"%PDF") and len(pdf) > 10_000
            # undo, so the next width starts from the same landmarks
            with page.expect_navigation(timeout=300_000):
                page.get_by_role("button", name="Undo the last correction").click(timeout=300_000)
            page.close()
        browser.close()
    assert not serious, "serious accessibility violations:\n" + "\n".join(serious)
