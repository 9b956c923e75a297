"""Who viewed, downloaded, changed which patient's data, and who signed in, from where: each leaves an AuditEvent."""

import pytest

from clinic.models import AuditEvent
from tests.patient_records import patient_with_records


@pytest.mark.django_db
def test_it_records_a_clinician_viewing_a_patient_page(client, clinic, charlie):
    patient, _, _ = patient_with_records(clinic)
    client.force_login(charlie)
    before = AuditEvent.objects.count()
    assert client.get(f"/patients/{patient.pk}/", REMOTE_ADDR="10.1.2.3").status_code == 200
    e = AuditEvent.objects.get(action=AuditEvent.VIEW)
    assert (e.user, e.username, e.patient_id, e.clinic_id) == (charlie, "charlie", patient.pk, clinic.pk)
    assert (e.object_type, e.object_id, e.method, e.path, e.status, e.remote_addr) == (
        "patient", str(patient.pk), "GET", f"/patients/{patient.pk}/", 200, "10.1.2.3")
    assert AuditEvent.objects.count() == before + 1  # one page, one event


@pytest.mark.django_db
def test_it_records_a_rig_downloading_a_result_and_a_user_downloading_one(client, clinic, small_rig, charlie):
    rig, key = small_rig
    patient, recs, _ = patient_with_records(clinic, rig)
    job = recs[1].job
    r = client.get(f"/api/jobs/{job.uid}/files/torso.ply", HTTP_AUTHORIZATION=f"Bearer {key}",
                   REMOTE_ADDR="10.0.0.7")
    assert r.status_code == 200
    e = AuditEvent.objects.get(action=AuditEvent.DOWNLOAD)
    assert (e.user, e.rig_serial, e.patient_id, e.clinic_id, e.remote_addr) == (
        None, rig.serial, patient.pk, clinic.pk, "10.0.0.7")
    assert (e.object_type, e.object_id, e.status) == ("job", str(job.uid), 200)

    client.force_login(charlie)
    assert client.get(f"/api/jobs/{job.uid}/files/report.json").status_code == 200
    e = AuditEvent.objects.filter(action=AuditEvent.DOWNLOAD, username="charlie").get()
    assert (e.patient_id, e.path) == (patient.pk, f"/api/jobs/{job.uid}/files/report.json")


@pytest.mark.django_db
def test_it_records_a_refused_look_at_another_clinics_patient(client, clinic, olga):
    patient, _, _ = patient_with_records(clinic)
    client.force_login(olga)
    assert client.get(f"/visits/{patient.visits.first().pk}/").status_code == 404
    e = AuditEvent.objects.get(action=AuditEvent.VIEW)
    assert (e.username, e.patient_id, e.object_type, e.status) == ("olga", patient.pk, "visit", 404)


@pytest.mark.django_db
def test_it_records_a_staff_user_changing_a_patient_on_the_page_and_creating_a_visit_in_the_api(client, clinic, ada):
    patient, _, _ = patient_with_records(clinic)
    client.force_login(ada)
    r = client.post(f"/patients/{patient.pk}/edit", {"identifier": "P-1", "name": "Robin Audit", "sex": "F",
                                                      "notes": "brace since June"}, REMOTE_ADDR="10.9.9.9")
    assert r.status_code == 302
    e = AuditEvent.objects.get(action=AuditEvent.CHANGE, username="ada")
    assert (e.user, e.patient_id, e.object_type, e.object_id, e.method, e.remote_addr) == (
        ada, patient.pk, "patient", str(patient.pk), "POST", "10.9.9.9")

    r = client.post(f"/api/patients/{patient.pk}/visits", {"date": "2027-01-05", "reason": "brace check"},
                    content_type="application/json")
    assert r.status_code == 201
    e = AuditEvent.objects.get(action=AuditEvent.CREATE, username="ada")
    assert (e.username, e.patient_id, e.object_type, e.object_id) == ("ada", patient.pk, "visit", str(r.json()["id"]))


@pytest.mark.django_db
def test_it_records_an_admin_change_page_seen_by_a_superuser(admin_client, clinic):
    patient, _, _ = patient_with_records(clinic)
    assert admin_client.get(f"/admin/clinic/patient/{patient.pk}/change/").status_code == 200
    e = AuditEvent.objects.get(action=AuditEvent.VIEW)
    assert (e.username, e.patient_id, e.object_type) == ("admin", patient.pk, "patient")
    assert admin_client.get(f"/admin/clinic/auditevent/?patient_id={patient.pk}").status_code == 200
    assert admin_client.get("/admin/clinic/auditevent/?q=robin").status_code == 200


@pytest.mark.django_db
def test_it_records_sign_ins_and_failed_sign_ins(client, charlie):
    r = client.post("/accounts/login/", {"username": "charlie", "password": "wrong"}, REMOTE_ADDR="10.4.4.4")
    assert r.status_code == 200
    r = client.post("/accounts/login/", {"username": "charlie", "password": "pw-charlie"}, REMOTE_ADDR="10.4.4.4")
    assert r.status_code == 302
    failed, ok = AuditEvent.objects.filter(action__in=[AuditEvent.LOGIN, AuditEvent.LOGIN_FAILED]).order_by("id")
    assert (failed.action, failed.user, failed.username, failed.remote_addr) == (
        AuditEvent.LOGIN_FAILED, None, "charlie", "10.4.4.4")
    assert (ok.action, ok.user, ok.username, ok.remote_addr) == (AuditEvent.LOGIN, charlie, "charlie", "10.4.4.4")


@pytest.mark.django_db
def test_a_job_writing_results_acts_for_nobody(clinic, charlie, rf):
    """A task run in-process inside a request is the job's doing, not the requester's."""
    from clinic import audit
    from clinic.models import Patient

    request = rf.get("/")
    request.user = charlie
    with_request = audit.AuditMiddleware(lambda req: _in_task_and_out(req, clinic))
    with_request(request)
    by = dict(AuditEvent.objects.filter(action=AuditEvent.CREATE, object_type="patient").values_list("object_id", "username"))
    job_made, user_made = Patient.objects.get(identifier="P-job"), Patient.objects.get(identifier="P-user")
    assert by == {str(job_made.pk): "", str(user_made.pk): "charlie"}


def _in_task_and_out(request, clinic):
    from celery.signals import task_postrun, task_prerun
    from django.http import HttpResponse

    from clinic.models import Patient

    task_prerun.send(sender=None, task_id="t1", task=None)
    Patient.objects.create(clinic=clinic, identifier="P-job", name="Made by a job")
    task_postrun.send(sender=None, task_id="t1", task=None)
    Patient.objects.create(clinic=clinic, identifier="P-user", name="Made by charlie")
    return HttpResponse()
