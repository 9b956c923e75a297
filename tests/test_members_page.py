"""A clinic administrator manages the clinic's members: add an existing user, change a role, remove."""

import pytest

from clinic.models import Member


@pytest.mark.django_db
def test_it_adds_changes_and_removes_a_member(client, ada, clinic, nobody):
    client.force_login(ada)
    assert client.get(f"/clinics/{clinic.pk}/members/").status_code == 200
    r = client.post(f"/clinics/{clinic.pk}/members/add", {"username": "nobody", "role": "technician"})
    assert r.status_code == 302
    m = Member.objects.get(clinic=clinic, user=nobody)
    assert m.role == Member.TECHNICIAN
    assert client.post(f"/clinics/{clinic.pk}/members/{m.pk}/role", {"role": "clinician"}).status_code == 302
    m.refresh_from_db()
    assert m.role == Member.CLINICIAN
    assert client.post(f"/clinics/{clinic.pk}/members/{m.pk}/remove").status_code == 302
    assert not Member.objects.filter(pk=m.pk).exists()


@pytest.mark.django_db
def test_it_refuses_unknown_users_roles_and_duplicates(client, ada, charlie, clinic):
    client.force_login(ada)
    url = f"/clinics/{clinic.pk}/members/add"
    assert client.post(url, {"username": "ghost", "role": "clinician"}).status_code == 400
    assert client.post(url, {"username": "charlie", "role": "superuser"}).status_code == 400
    assert client.post(url, {"username": "charlie", "role": "administrator"}).status_code == 409
    assert Member.objects.get(clinic=clinic, user=charlie).role == Member.CLINICIAN


@pytest.mark.django_db
def test_it_keeps_one_administrator(client, ada, clinic):
    me = Member.objects.get(clinic=clinic, user=ada)
    client.force_login(ada)
    assert client.post(f"/clinics/{clinic.pk}/members/{me.pk}/role", {"role": "clinician"}).status_code == 409
    assert client.post(f"/clinics/{clinic.pk}/members/{me.pk}/remove").status_code == 409
    assert Member.objects.get(pk=me.pk).role == Member.ADMINISTRATOR


@pytest.mark.django_db
def test_it_is_for_administrators_only(client, alice, charlie, olga, clinic):
    target = Member.objects.get(clinic=clinic, user=charlie)
    for user, status in ((alice, 403), (charlie, 403), (olga, 404)):
        client.force_login(user)
        assert client.get(f"/clinics/{clinic.pk}/members/").status_code == status
        assert client.post(f"/clinics/{clinic.pk}/members/{target.pk}/role",
                           {"role": "administrator"}).status_code == status
        assert client.post(f"/clinics/{clinic.pk}/members/{target.pk}/remove").status_code == status
    target.refresh_from_db()
    assert target.role == Member.CLINICIAN
