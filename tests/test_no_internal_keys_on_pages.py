"""No internal key of the analysis (``surface_rotation_deg.max``, ``hump_angle_deg``...) reaches a page."""

import pytest

from tests.test_browser_comparison import compared, patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_no_key_of_the_flattened_indices_appears_in_any_page(client, charlie, patient_with_two_visits):  # noqa: F811
    from analysis.repeatability import INDEX_FIGURES, flatten
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    first, second = p.visits.all()
    compared(p)
    recs = list(Reconstruction.objects.filter(session__visit__patient=p))
    keys = set(INDEX_FIGURES)
    for rec in recs:
        keys |= set(flatten(rec.indices))
    keys |= {k.split(".")[0] for k in keys if "_" in k.split(".")[0]}  # the top-level names too
    client.force_login(charlie)
    pages = ["/", f"/patients/{p.pk}/", f"/visits/{first.pk}/", f"/visits/{second.pk}/",
             f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}",
             f"/pictures/reconstruction/{recs[0].pk}/asymmetry/"]
    for url in pages:
        html = client.get(url).content.decode()
        leaked = sorted(k for k in keys if k in html)
        assert not leaked, f"{url} shows internal keys {leaked}"
        assert "the paper" not in html and "Table 1" not in html, url
