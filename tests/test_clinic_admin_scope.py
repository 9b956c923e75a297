"""A clinic administrator with staff access is no superuser: no Django admin, nothing of another clinic."""

import pytest

from clinic.models import Patient, RigKey


@pytest.fixture
def other_rig(other_clinic):
    from clinic.models import Rig

    return Rig.objects.create(clinic=other_clinic, serial="SOUTH-1", description={})


@pytest.mark.django_db
def test_it_keeps_a_clinic_administrator_out_of_the_admin(client, ada):
    client.force_login(ada)
    for url in ("/admin/", "/admin/clinic/patient/", "/admin/clinic/rig/"):
        r = client.get(url)
        assert r.status_code == 302 and r["Location"].startswith("/admin/login/"), url
    client.logout()
    r = client.post("/admin/login/", {"username": "ada", "password": "pw-ada", "next": "/admin/"})
    assert r.status_code == 200 and b"for superusers" in r.content
    assert "_auth_user_id" not in client.session


@pytest.mark.django_db
def test_it_lets_a_superuser_into_the_admin(admin_client):
    assert admin_client.get("/admin/clinic/patient/").status_code == 200


@pytest.mark.django_db
def test_it_shows_a_clinic_administrator_nothing_of_another_clinic(client, ada, other_clinic, other_rig):
    theirs = Patient.objects.create(clinic=other_clinic, identifier="S-1", name="Sam Southside")
    client.force_login(ada)
    assert b"Sam Southside" not in client.get("/").content
    assert client.get(f"/patients/{theirs.pk}/").status_code == 404
    assert client.get(f"/rigs/{other_rig.serial}/").status_code == 404
    assert client.post(f"/rigs/{other_rig.serial}/keys").status_code == 404
    assert client.post(f"/api/rigs/{other_rig.serial}/keys").status_code == 404
    _, key = RigKey.issue(other_rig)
    assert client.post(f"/rigs/{other_rig.serial}/keys/{key[:10]}/revoke").status_code == 404
    assert client.get(f"/clinics/{other_clinic.pk}/members/").status_code == 404
    assert client.post(f"/clinics/{other_clinic.pk}/members/add",
                       {"username": "ada", "role": "administrator"}).status_code == 404
    assert other_rig.keys.count() == 1 and other_rig.keys.get().revoked is None
    assert not other_clinic.members.filter(user=ada).exists()
