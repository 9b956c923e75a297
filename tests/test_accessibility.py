"""Every page a clinician sees passes an automated accessibility check (axe-core) without a serious violation.

axe-core (MPL-2.0, tests/vendor/axe-core/, version in its README) is injected into each page in the machine's
Chromium, driven by Playwright as in tests/test_browser_comparison.py, at a desktop's width (1280 px) and a phone's
(390 px). A violation of impact "serious" or "critical" fails the test; the message lists each with its rule id,
impact, page, width and the offending elements. "moderate" and "minor" ones are printed (pytest -s shows them).

What axe cannot judge alone the other tests here check by reading the templates: a skip link, a ``scope`` on
every table header, alt text on every picture, flags carried by a symbol or words as well as colour.
"""

import re
from pathlib import Path

import pytest

from tests.test_browser_comparison import CHROMIUM, chromium_or_skip, compared, patient_with_two_visits  # noqa: F401

AXE = Path(__file__).resolve().parent / "vendor" / "axe-core" / "axe.min.js"
WIDTHS = (1280, 390)
SERIOUS = ("serious", "critical")


def axe_violations(page) -> list[dict]:
    """axe's violations on the page as it is now (the vendored copy, injected as a file: no network).

    The pages' Content-Security-Policy allows no inline script, so the pages are opened with ``bypass_csp``.
    """
    if not page.evaluate("typeof axe !== 'undefined'"):
        page.add_script_tag(path=str(AXE))
    return page.evaluate("""async () => {
        const r = await axe.run(document, {resultTypes: ['violations']});
        return r.violations.map(v => ({id: v.id, impact: v.impact, help: v.help,
                                       targets: v.nodes.map(n => n.target.join(' '))}));
    }""")


def _log_in(page, base, username):
    page.goto(f"{base}/accounts/login/")
    page.fill("#id_username", username)
    page.fill("#id_password", "pw-" + username)
    page.click("button[type=submit]")
    page.wait_for_url(f"{base}/")


def _check(page, name, found):
    """The page at each width in turn (resized in place: one load, one injection of axe per page)."""
    page.wait_for_load_state("load")
    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 900})
        for v in axe_violations(page):
            found.append({**v, "page": name, "width": width, "url": page.url})


@pytest.mark.django_db(transaction=True)
def test_no_page_has_a_serious_accessibility_violation(live_server, patient_with_two_visits,  # noqa: F811
                                                        ada, settings):
    chromium_or_skip()
    from playwright.sync_api import sync_playwright

    settings.DEBUG = False  # the friendly 404 and 403 pages, as in production (Django's technical pages otherwise)
    p = patient_with_two_visits
    first, second = p.visits.all()
    compared(p)
    base = live_server.url
    clinician_pages = {
        "worklist": "/", "patient list": "/?q=Robin", "patient history": f"/patients/{p.pk}/",
        "visit": f"/visits/{second.pk}/",
        "comparison": f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}",
        "new patient form": "/patients/new", "edit patient form": f"/patients/{p.pk}/edit",
        "new visit form": f"/patients/{p.pk}/visits/new", "edit visit form": f"/visits/{second.pk}/edit",
        "rig": "/rigs/RIG-B/", "not found (404)": "/patients/999999/",
        "not allowed (403)": f"/clinics/{p.clinic_id}/members/",
    }
    found: list[dict] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--headless=new"])
        page = browser.new_page(bypass_csp=True)
        page.goto(f"{base}/accounts/login/")
        _check(page, "sign in", found)
        page.fill("#id_username", "nobody")  # not a user: no one's failed sign-ins count towards a lock
        page.fill("#id_password", "wrong")
        page.click("button[type=submit]")
        _check(page, "sign in, refused", found)
        _log_in(page, base, "charlie")
        for name, url in clinician_pages.items():
            page.goto(base + url, timeout=300_000)  # the comparison is computed when first opened
            _check(page, name, found)
            if name == "visit":
                picture = page.locator(".pics a").first.get_attribute("href")
            if name == "comparison":
                page.locator("details.technical summary").click()
                _check(page, "comparison, technical details open", found)
        page.goto(base + picture)
        _check(page, "picture", found)
        page.goto(f"{base}/patients/new")
        page.click("form.form button[type=submit]")  # empty: the form comes back with its errors marked
        assert page.locator("[aria-invalid=true]").count(), "the empty form came back without its errors"
        _check(page, "new patient form with errors", found)
        page.close()
        # the administrator's pages (members, rig keys) as the clinic's administrator
        page = browser.new_page(bypass_csp=True)
        _log_in(page, base, "ada")
        for name, url in {"members": f"/clinics/{p.clinic_id}/members/", "rig with keys": "/rigs/RIG-B/"}.items():
            page.goto(base + url)
            _check(page, name, found)
        page.click("text=Issue a new key")
        _check(page, "rig with a new key", found)
        browser.close()

    for v in found:
        if v["impact"] not in SERIOUS:
            print(f"axe ({v['impact']}): {v['id']} on {v['page']} at {v['width']} px: {v['targets']}")
    serious = [v for v in found if v["impact"] in SERIOUS]
    assert not serious, "serious accessibility violations (axe-core):\n" + "\n".join(
        f"- {v['id']} ({v['impact']}: {v['help']}) on {v['page']} at {v['width']} px, {v['url']}: "
        + "; ".join(v["targets"]) for v in serious)


TEMPLATES = Path(__file__).resolve().parent.parent / "templates"


def test_every_page_has_a_skip_link_to_its_content():
    base = (TEMPLATES / "base.html").read_text()
    assert 'class="skip" href="#main"' in base and '<main id="main"' in base


def test_every_table_header_has_a_scope_and_every_picture_an_alt_text():
    for path in sorted(TEMPLATES.rglob("*.html")):
        html = path.read_text()
        for th in re.findall(r"<th\b[^>]*>", html):
            assert "scope=" in th, f"{path.relative_to(TEMPLATES)}: table header without scope: {th}"
        for img in re.findall(r"<img\b[^>]*>", html):
            assert re.search(r'\balt="[^"]+', img), f"{path.relative_to(TEMPLATES)}: picture without alt text: {img}"


def test_flags_are_carried_by_words_or_a_symbol_as_well_as_colour():
    """A red or green mark is never the only sign: the element says it (beyond noise, ▲, ✓, unstable, ...)."""
    for path in sorted(TEMPLATES.rglob("*.html")):
        html = path.read_text()
        for m in re.finditer(r'<(span|td|p)\b[^>]*class="[^"]*\b(flag|ok|warn)\b[^"]*"[^>]*>(.*?)</\1>', html, re.S):
            words = re.sub(r"<[^>]+>|\{[%{].*?[%}]\}", "", m.group(3)).strip()
            assert words, f"{path.relative_to(TEMPLATES)}: a {m.group(2)} mark with only colour: {m.group(0)[:120]}"
