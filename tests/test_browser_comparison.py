"""A clinician in a real browser: logs in, opens a patient, opens a comparison, sees its deformation map.

Playwright (Python) drives the machine's Chromium (Debian's ``chromium``
package; Playwright cannot download its own browser here).
"""

import functools
import os
import shutil

import pytest
from django.core.files.base import ContentFile

from tests.analysis_cache import reuse_analyses

CHROMIUM = os.environ.get("CHROMIUM", shutil.which("chromium") or "/usr/bin/chromium")


def chromium_or_skip():
    if not os.path.exists(CHROMIUM):
        message = f"Chromium not found at {CHROMIUM} (Debian package chromium)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + "; CI requires it")
        pytest.skip(message)


@functools.lru_cache(maxsize=None)
def torso_ply(rotation_deg, seed):
    """The PLY bytes of a synthetic back (bytes: the cached value cannot be changed by a caller)."""
    import tempfile
    from pathlib import Path

    from analysis.synthetic import synthetic_back
    from recon_engine.surface import write_ply

    torso, _ = synthetic_back(rotation_deg=rotation_deg, lateral_mm=rotation_deg, spacing_mm=5.0, noise_mm=0.05,
                              seed=seed)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "torso.ply"
        write_ply(path, torso.points, torso.normals)
        return path.read_bytes()


@pytest.fixture
def patient_with_two_visits(clinic, charlie, monkeypatch):
    from clinic.analysis_step import analyse_reconstruction
    from clinic.models import CaptureSession, Job, Patient, Reconstruction, Rig, Visit

    reuse_analyses(monkeypatch)
    rig = Rig.objects.create(clinic=clinic, serial="RIG-B", description={})
    patient = Patient.objects.create(clinic=clinic, identifier="P-77", name="Robin Browser")
    for k, (date, rotation) in enumerate((("2026-07-01", 5.0), ("2026-11-01", 10.0))):
        visit = Visit.objects.create(patient=patient, date=date, reason=f"visit {k}")
        session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                                manifest_sha256=str(k), idempotency_key=str(k), captured_at=date,
                                                state=CaptureSession.FINALIZED)
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED,
                                 percent=100, stage="done")
        rec = Reconstruction(job=job, session=session, status="ok", points=1, report={"registration": {"pairs": []}})
        rec.torso.save("torso.ply", ContentFile(torso_ply(rotation, k)), save=False)
        rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
        rec.save()
        analyse_reconstruction(rec)
    return patient


def compared(patient):
    """The patient's two visits compared, as the comparison page's POST asks (jobs run in-process here): the pages
    that list the comparison's then show it, not its "compare these scans" button."""
    from clinic import pipeline
    from clinic.models import Comparison, Reconstruction

    first, second = Reconstruction.objects.filter(session__visit__patient=patient).order_by("session__visit__date")
    pipeline.request_comparison(first, second)
    return Comparison.objects.get(earlier=first, later=second)


@pytest.mark.django_db(transaction=True)
def test_a_clinician_opens_a_comparison_and_its_deformation_map_loads(live_server, patient_with_two_visits):
    chromium_or_skip()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
        page = browser.new_page()
        page.goto(f"{live_server.url}/")
        assert "/accounts/login/" in page.url
        page.fill("#id_username", "charlie")
        page.fill("#id_password", "pw-charlie")
        page.click("button[type=submit]")
        page.wait_for_url(f"{live_server.url}/")
        page.fill("input[name=q]", "Robin")
        page.click("text=Search")
        page.click("text=Robin Browser")
        assert page.locator("h1").inner_text().startswith("Robin Browser")
        # the comparison (registration and pictures) is computed by a job that the form's POST starts: in the
        # embedded default it runs within the request, elsewhere the page shows its progress until the result is there
        with page.expect_navigation(timeout=300_000):
            page.click("button:has-text('Compare')", no_wait_after=True)
        page.wait_for_selector("#deformation", timeout=300_000)
        loaded = page.eval_on_selector("#deformation", "img => img.complete && img.naturalWidth > 0")
        assert loaded, "the deformation picture did not load"
        assert "Indices" in page.content()
        browser.close()
