"""The history's trend picture is drawn once per state of the scans and noise, then served from storage."""

import pytest

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_the_trend_is_served_from_the_cache_on_the_second_request(client, charlie, patient_with_two_visits,  # noqa: F811
                                                                    monkeypatch):
    from analysis import pictures
    from clinic.models import Reconstruction

    calls = []
    draw = pictures.trend_picture

    def counting(*args, **kw):
        calls.append(1)
        return draw(*args, **kw)

    monkeypatch.setattr(pictures, "trend_picture", counting)
    client.force_login(charlie)
    url = f"/patients/{patient_with_two_visits.pk}/trend.png"
    first = client.get(url)
    assert first.status_code == 200 and first["Content-Type"] == "image/png" and len(calls) == 1
    second = client.get(url)
    body = b"".join(second.streaming_content)
    assert second.status_code == 200 and body == first.content and len(calls) == 1  # not drawn again
    # new indices (e.g. a landmark corrected) are a new state: drawn again
    rec = Reconstruction.objects.filter(session__visit__patient=patient_with_two_visits).first()
    rec.indices = {**rec.indices, "hump_mm": 99.0}
    rec.save()
    assert client.get(url).status_code == 200 and len(calls) == 2
    # only the latest state's picture stays in storage
    from django.core.files.storage import default_storage
    assert len(default_storage.listdir(f"trends/patient-{patient_with_two_visits.pk}")[1]) == 1
