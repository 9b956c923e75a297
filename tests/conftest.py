"""Shared fixtures: simulated tiny installations, generated once per test run (whatever the number of workers)."""

import fcntl
import os
from dataclasses import replace

import pytest

from recon_engine.simulator.config import preset
from recon_engine.simulator.scenario import simulate


def pytest_configure(config):
    """The matching's compiled kernels loaded once, in the run's first process, before any worker starts.

    numba compiles them on first use (about 24 s of one core) and caches the
    machine code beside the source; in a fresh clone every process that got
    there before the cache was written (pytest's workers, the engine's arm
    processes, Celery's children) compiled them again.
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        from recon_engine.kernels import warm_up

        warm_up()


# Test files by what they cost (seconds of wall time of one worker, two workers on 2 cores, Intel Xeon, measured
# 2026-12-07 before the comparisons read stored indices), the costliest first. pytest-xdist hands each worker whole
# files in collection order (make test turns its own reordering, by the number of tests in a file, off): the long
# single-test files of real processes would otherwise come last and leave the other workers idle at the end.
COST_S = {
    "test_stability.py": 151, "test_browser_clinic_day.py": 144, "test_reconstruct_torso.py": 80,
    "test_service_flow_postgres.py": 78, "test_worker_killed.py": 71, "test_broker_outage.py": 46,
    "test_bundle_outage.py": 43, "test_analysis_indices.py": 40, "test_pipeline_comparisons.py": 39,
    "test_accessibility.py": 37, "test_report_pdf.py": 35, "test_job_leases.py": 33,
    "test_service_flow_embedded.py": 32, "test_registration_taken_over.py": 29, "test_landmark_correction.py": 28,
    "test_arms_crossed_before_the_chest.py": 27, "test_analysis_landmarks.py": 23, "test_analysis_facing.py": 22,
    "test_a_scan_cut_on_the_neck_asks_for_the_vertebra_prominens.py": 21, "test_analysis_compare.py": 21,
    "test_backup_restore_postgres.py": 20, "test_bench_service_runs.py": 20, "test_api_rejects_bad_fields.py": 20,
    "test_simulator_conditions.py": 19, "test_browser_comparison.py": 18, "test_production_settings.py": 17,
    "test_backup_restore.py": 17, "test_registration_rims.py": 16,
}


def pytest_collection_modifyitems(config, items):
    """The costliest files first (``COST_S``), each file's tests in their own order; the rest as collected."""
    items.sort(key=lambda item: -COST_S.get(item.path.name, 0))  # stable: a file's tests keep their order


def simulated_once(tmp_path_factory, name, cfg):
    """The scenario ``cfg`` simulated into a folder all of the run's workers share; the first one in simulates.

    Under pytest-xdist each worker is its own process with its own session
    fixtures: without this, both workers would render the same scenarios. A
    lock on a file beside the folder makes the others wait for the first; the
    simulator writes into a temporary folder and renames it, so a folder that
    exists is whole.
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, above each worker's own
    shared = root / "simulated"
    shared.mkdir(exist_ok=True)
    out = shared / name
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.exists():
            simulate(out, cfg, progress=lambda msg: None)
    return out


def _testfield_only(tmp_path_factory, name, captures=(), **kw):
    return simulated_once(tmp_path_factory, name, preset("tiny", seed=11, captures=captures, **kw))


# the engine's tests read visit0-a; the simulator's own tests also the later visit (one scenario for both). They
# use the true calibration, so one test-field pose (the files' format is checked on it), not the preset's three:
# 60 images rendered instead of 100
TORSO_SCENARIO = preset("tiny", seed=0, captures=(("visit0-a", 0), ("visit1-a", 1)))
TORSO_SCENARIO = replace(TORSO_SCENARIO, testfield=replace(TORSO_SCENARIO.testfield, poses=1))


@pytest.fixture(scope="session")
def rig_session_1(tmp_path_factory):
    """Test-field captures of a tiny rig (3 poses), session 1, and one torso capture (visit0-a)."""
    return _testfield_only(tmp_path_factory, "session1", captures=(("visit0-a", 0),), session=1)


@pytest.fixture(scope="session")
def rig_session_2(tmp_path_factory):
    """The same rig, unchanged, on another day (other poses, other noise)."""
    return _testfield_only(tmp_path_factory, "session2", session=2)


@pytest.fixture(scope="session")
def rig_disturbed(tmp_path_factory):
    """The same rig with two lenses knocked: A3 principal distance +1%, C2 principal point +3 px.

    At the tiny preset (480x320 px, pixels 6.25 times the paper's) a
    calibration determines the principal point only to about 2.5 px (it
    trades off against the camera's rotation), so ZROT cannot see a 3 px
    shift; the camera's bundle in its arm (ARM) can. The benchmark checks the
    paper's 0.1% and 2 px at paper scale.
    """
    return _testfield_only(tmp_path_factory, "disturbed", session=3,
                           lens_changes=(("A3", "pd", 0.01), ("C2", "pp_x", 3.0)))


def _calibrate(scenario):
    from recon_engine.calibration import calibrate
    from recon_engine.formats import read_capture, read_rig, read_testfield

    rig = read_rig(scenario / "rig.json")
    tf = read_testfield(scenario / "testfield.json")
    caps = [read_capture(p, rig) for p in sorted((scenario / "captures").glob("testfield-pose*"))]
    return calibrate(caps, rig, tf)


@pytest.fixture(scope="session")
def calibration_1(rig_session_1):
    return _calibrate(rig_session_1)


@pytest.fixture(scope="session")
def calibration_2(rig_session_2):
    return _calibrate(rig_session_2)


@pytest.fixture(scope="session")
def calibration_disturbed(rig_disturbed):
    return _calibrate(rig_disturbed)


@pytest.fixture(scope="session")
def torso_scenario(tmp_path_factory):
    """A tiny scenario with a torso capture (visit0-a) and a later visit's (visit1-a), arms displaced."""
    return simulated_once(tmp_path_factory, "torso", TORSO_SCENARIO)



# --- the clinic service: a few named users, one with no access ---------------------

@pytest.fixture(scope="session")
def django_db_modify_db_settings(django_db_modify_db_settings_parallel_suffix, tmp_path_factory):
    """The SQLite test database in a file, as the demo's, not Django's shared in-memory one.

    With an in-memory database the live server's request threads share the
    test thread's connection object; two requests in flight at once (a page
    and its pictures) then leave its transaction state broken for the tests
    that follow. A file gives each thread its own connection.
    """
    from django.conf import settings

    db = settings.DATABASES["default"]
    if db["ENGINE"].endswith("sqlite3"):
        db.setdefault("TEST", {})["NAME"] = str(tmp_path_factory.mktemp("database") / "test.sqlite3")


@pytest.fixture(autouse=True)
def _media_in_tmp(settings, tmp_path):
    """Each test's stored files in its own folder (never the repository's var/)."""
    settings.STORAGES = {**settings.STORAGES, "default": {
        "BACKEND": "django.core.files.storage.FileSystemStorage", "OPTIONS": {"location": str(tmp_path / "media")}}}
    settings.WORK_DIR = str(tmp_path / "work")

@pytest.fixture
def clinic(db):
    from clinic.models import Clinic

    return Clinic.objects.create(name="Northside Scoliosis Clinic")


@pytest.fixture
def other_clinic(db):
    from clinic.models import Clinic

    return Clinic.objects.create(name="Southside Clinic")


def _user(name, clinic=None, role=None):
    from django.contrib.auth.models import User

    from clinic.models import Member

    user = User.objects.create_user(name, f"{name}@example.org", "pw-" + name)
    if clinic is not None:
        Member.objects.create(clinic=clinic, user=user, role=role)
    return user


@pytest.fixture
def alice(clinic):
    """A technician of the clinic: registers rigs and test fields."""
    from clinic.models import Member

    return _user("alice", clinic, Member.TECHNICIAN)


@pytest.fixture
def charlie(clinic):
    """A clinician of the clinic: patients and visits, no rigs."""
    from clinic.models import Member

    return _user("charlie", clinic, Member.CLINICIAN)


@pytest.fixture
def ada(clinic):
    """An administrator of the clinic: its members and rig keys (staff, not a superuser)."""
    from clinic.models import Member

    user = _user("ada", clinic, Member.ADMINISTRATOR)
    user.is_staff = True
    user.save(update_fields=["is_staff"])
    return user


@pytest.fixture
def olga(other_clinic):
    """An administrator of another clinic."""
    from clinic.models import Member

    return _user("olga", other_clinic, Member.ADMINISTRATOR)


@pytest.fixture
def nobody(db):
    """A user with no clinic."""
    return _user("nobody")


@pytest.fixture
def small_rig(clinic):
    """The boundary tests' small rig (3 cameras of 40 x 30 px), registered; ``(rig, key)``."""
    from clinic.api import sync_cameras
    from clinic.models import Rig, RigKey, TestField
    from recon_engine.formats import rig_from_dict
    from tests.boundary_fixtures import RIG

    rig = Rig.objects.create(clinic=clinic, serial=RIG["serial"], description=RIG)
    sync_cameras(rig, rig_from_dict(RIG))
    TestField.objects.create(clinic=clinic, name="tower", description={})
    return rig, RigKey.issue(rig)[1]
