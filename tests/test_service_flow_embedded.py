"""The clinic's whole flow through the HTTP API on the embedded default (SQLite, jobs in-process)."""

import pytest
from django.conf import settings

from clinic.models import Calibration, Camera, Patient, StabilityCheck, Visit
from tests.service_flow import ClientApi, assert_same_as_engine, register_rig, run_flow


@pytest.mark.django_db(transaction=True)
def test_the_whole_flow_runs_in_process(client, alice, clinic, rig_session_1, rig_session_2, tmp_path):
    assert settings.CELERY_TASK_ALWAYS_EAGER and settings.DATABASES["default"]["ENGINE"].endswith("sqlite3")
    api = ClientApi(client)
    api.login("alice", "pw-alice")
    key = register_rig(api, clinic.pk, rig_session_1)
    patient = Patient.objects.create(clinic=clinic, identifier="P-1", name="Test Patient")
    visit = Visit.objects.create(patient=patient)
    steps = run_flow(api, key, rig_session_1, rig_session_2, visit.pk, tmp_path / "out")

    assert Calibration.objects.count() == 2
    cameras = Camera.objects.count()
    assert cameras == 20 and StabilityCheck.objects.count() == cameras
    # the same rig on another day: every camera stable, so the rig is not flagged
    assert StabilityCheck.objects.filter(stable=True).count() == cameras
    # every camera has two others in its arm: the ARM measure is stored beside ZROT, ROT and SPR
    assert StabilityCheck.objects.exclude(arm_px=None).count() == cameras
    assert steps["torso_job"]["percent"] == 100 and steps["torso_job"]["result"]["status"] in ("ok", "partial")
    assert_same_as_engine(tmp_path / "out", rig_session_1)
