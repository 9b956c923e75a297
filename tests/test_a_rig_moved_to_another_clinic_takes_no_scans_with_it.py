"""A rig handed to another clinic takes none of its patients' scans with it.

A patient's scan belongs to the patient's clinic (``clinic.models.captures_of``); before, pictures, torso
files and session status were scoped by the rig's clinic, so after a superuser moved a rig its old patients'
scans were shown to the new clinic and hidden from their own.
"""
import pytest

from clinic.models import Rig, RigKey
from tests.patient_records import patient_with_records


def _scan_urls(recs, comp):
    rec = recs[0]
    return [f"/pictures/reconstruction/{rec.pk}/back/", f"/pictures/reconstruction/{rec.pk}/back.png",
            f"/pictures/comparison/{comp.pk}/map/", f"/pictures/comparison/{comp.pk}/map.png",
            f"/api/jobs/{rec.job.uid}/files/torso.ply", f"/api/jobs/{rec.job.uid}",
            f"/api/sessions/{rec.session.uid}"]


@pytest.fixture
def moved(clinic, other_clinic):
    p, recs, comp = patient_with_records(clinic)
    Rig.objects.filter(serial="RIG-R").update(clinic=other_clinic)  # as the admin's rig form may do
    return p, recs, comp


@pytest.mark.django_db
def test_it_hides_the_old_clinics_scans_from_the_new_clinic(client, olga, moved):
    _, recs, comp = moved
    client.force_login(olga)
    for url in _scan_urls(recs, comp):
        assert client.get(url).status_code == 404, url


@pytest.mark.django_db
def test_it_keeps_the_scans_with_the_patients_clinic(client, charlie, moved):
    _, recs, comp = moved
    client.force_login(charlie)
    for url in _scan_urls(recs, comp):
        r = client.get(url)
        assert r.status_code == 200, url


@pytest.mark.django_db
def test_the_moved_rigs_key_reads_none_of_its_old_patients_scans(client, moved):
    _, recs, _ = moved
    rig = Rig.objects.get(serial="RIG-R")
    _, secret = RigKey.issue(rig)
    auth = {"HTTP_AUTHORIZATION": f"Bearer {secret}"}
    assert client.get(f"/api/sessions/{recs[0].session.uid}", **auth).status_code == 404
    assert client.get(f"/api/jobs/{recs[0].job.uid}/files/torso.ply", **auth).status_code == 404
