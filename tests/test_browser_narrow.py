"""At a phone's width (390 px) no page scrolls sideways: tables scroll in their own box, pictures shrink.

Playwright on the machine's Chromium, as tests/test_browser_comparison.py. Screenshots at 1280 and 390 px go
to a temporary folder, or to docs/screenshots/ with SAVE_SCREENSHOTS=1.
"""

import os
from pathlib import Path

import pytest

from tests.test_browser_comparison import CHROMIUM, chromium_or_skip, compared, patient_with_two_visits  # noqa: F401


@pytest.mark.django_db(transaction=True)
def test_no_page_scrolls_sideways_at_390_px(live_server, patient_with_two_visits, tmp_path):  # noqa: F811
    chromium_or_skip()
    from playwright.sync_api import sync_playwright

    p = patient_with_two_visits
    first, second = p.visits.all()
    compared(p)
    out = Path(__file__).resolve().parent.parent / "docs" / "screenshots" if os.environ.get("SAVE_SCREENSHOTS") \
        else tmp_path
    out.mkdir(parents=True, exist_ok=True)
    pages = {"history": f"/patients/{p.pk}/", "visit": f"/visits/{second.pk}/",
             "comparison": f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}"}
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
        for width in (1280, 390):
            page = browser.new_page(viewport={"width": width, "height": 900})
            page.goto(f"{live_server.url}/accounts/login/")
            page.fill("#id_username", "charlie")
            page.fill("#id_password", "pw-charlie")
            page.click("button[type=submit]")
            page.wait_for_url(f"{live_server.url}/")
            for name, url in pages.items():
                page.goto(live_server.url + url, timeout=300_000)  # the comparison is computed when first opened
                page.wait_for_load_state("load")
                scroll, inner = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
                assert scroll <= inner, f"{name} scrolls sideways at {width} px ({scroll} > {inner})"
                assert page.locator(".patient-head, h1").first.inner_text().startswith("Robin Browser")
                page.screenshot(path=str(out / f"{name}-{width}.png"))
            page.close()
        browser.close()
    assert len(list(out.glob("*-390.png"))) == 3
