"""What a clinic does, on the embedded default: ``python manage.py demo``.

A reduced rig (the simulator's ``demo`` preset, or ``tiny``) is registered and calibrated
from simulated test-field captures; a patient gets a baseline visit, a
same-day re-scan and a visit four months later with progression. Everything
goes through the HTTP API (Django's in-process client) and runs as jobs
(in-process without a broker). The findings are printed, with how to open the
clinicians' pages.
"""

import json
import shutil
import time
from pathlib import Path

from django.contrib.auth.models import User
from django.core.management.base import BaseCommand, CommandError
from django.core.files.storage import default_storage
from django.db import transaction
from django.db.models import Q
from django.test import Client

from analysis.repeatability import flatten
from clinic import labels, records
from clinic.models import Clinic, Comparison, Job, Member, Patient, Reconstruction, Rig

DEMO_CLINIC = "Demo Scoliosis Clinic"
DEMO_USER, DEMO_PASSWORD = "demo", "demo-torsoscan"


class Command(BaseCommand):
    help = "Run the clinic's whole flow on a simulated rig and patient (embedded default)."

    def add_arguments(self, parser):
        parser.add_argument("--out", default="demo-out", help="where the simulated scenario is written")
        parser.add_argument("--seed", type=int, default=0)
        parser.add_argument("--reuse", action="store_true", help="reuse a scenario already simulated in --out")
        parser.add_argument("--preset", default="demo", choices=["tiny", "demo"],
                            help="the simulated rig: 'demo' (720 x 480 px cameras, about 3 mm between torso points; "
                                 "a few minutes) or 'tiny' (the tests' 480 x 320 px; sparse torsos, faster)")

    def say(self, msg):
        self.stdout.write(msg)

    def mark_what_was_not_found(self, client, rec, truth: Path, visit_id: int):
        """As a clinician would: the trunk's landmarks the analysis could not find with confidence are marked on
        the visit page (here at the simulator's true positions), and the indices are computed again."""
        from analysis.indices import CORE_LANDMARKS

        mark = [n for n in ((rec.indices or {}).get("not_measurable") or {}).get("mark", []) if n in CORE_LANDMARKS]
        if not mark:
            return rec
        true = json.loads((truth / "truth.json").read_text())["landmarks"]
        fields = {n: " ".join(f"{c:.1f}" for c in true[n]) for n in mark if n in true}
        r = client.post(f"/visits/{visit_id}/landmarks", fields)
        if r.status_code != 302:
            raise CommandError(f"marking {', '.join(fields)} failed: {r.status_code} {r.content[:300]!r}")
        self.say(f"  the {' and the '.join(labels.landmark(n) for n in fields)} could not be found with confidence: "
                 "a clinician marks it on the visit page (here at the simulator's true position), and the "
                 "indices are computed again")
        rec.refresh_from_db()
        return rec
        self.stdout.flush()

    def api(self, client, method, path, key=None, expect=(200, 201), **kw):
        extra = {"HTTP_AUTHORIZATION": f"Bearer {key}"} if key else {}
        if "json" in kw:
            kw = {"data": json.dumps(kw.pop("json")), "content_type": "application/json"}
        r = getattr(client, method)(path, **kw, **extra)
        if r.status_code not in expect:
            raise CommandError(f"{method.upper()} {path}: {r.status_code} {r.content[:500]!r}")
        return r.json()

    def upload(self, client, key, folder: Path, **extra):
        manifest = json.loads((folder / "capture.json").read_text())
        s = self.api(client, "post", "/api/sessions", key, json={"manifest": manifest, **extra})
        for im in manifest["images"]:
            self.api(client, "put", f"/api/sessions/{s['id']}/images/{im['camera']}", key,
                     data=(folder / im["file"]).read_bytes(), content_type="application/octet-stream")
        return self.api(client, "post", f"/api/sessions/{s['id']}/finalize", key)

    def handle(self, *args, out, seed, reuse, preset="demo", **kw):
        from recon_engine.simulator.config import preset as scenario_preset
        from recon_engine.simulator.scenario import simulate

        from django.db import connection
        from django.db.migrations.executor import MigrationExecutor

        # before minutes of simulation: a database without its tables (or behind the code) fails at once
        if MigrationExecutor(connection).migration_plan(MigrationExecutor(connection).loader.graph.leaf_nodes()):
            raise CommandError("the database is not migrated: run `manage.py migrate` first (`make demo` does)")
        t0 = time.perf_counter()
        scenario = Path(out) / "scenario"
        if not (reuse and (scenario / "rig.json").exists()):
            self.say(f"simulating a reduced rig and a patient with a scoliotic curve into {scenario} ...")
            if scenario.exists():
                shutil.rmtree(scenario)
            cfg = scenario_preset(preset, seed=seed, captures=(("visit0-a", 0), ("visit0-b", 0), ("visit1-a", 1)))
            simulate(scenario, cfg, progress=lambda m: None)
            self.say(f"  simulated in {time.perf_counter() - t0:.0f} s")

        named_before = records.all_stored_names()
        with transaction.atomic():  # a fresh demo clinic each run; other clinics are left alone
            rig_serial = json.loads((scenario / "rig.json").read_text())["serial"]
            rigs = Rig.objects.filter(Q(clinic__name=DEMO_CLINIC) | Q(serial=rig_serial))
            # jobs first: a job holds on to the calibration it used (protected), which goes with its rig
            Job.objects.filter(rig__in=rigs).delete()
            rigs.delete()
            Clinic.objects.filter(name=DEMO_CLINIC).delete()
            # the last run's files go once the rows that named them are gone
            transaction.on_commit(lambda: [default_storage.delete(n)
                                           for n in named_before - records.all_stored_names()])
            clinic = Clinic.objects.create(name=DEMO_CLINIC)
            user = User.objects.filter(username=DEMO_USER).first() or User.objects.create_user(DEMO_USER)
            user.set_password(DEMO_PASSWORD)
            user.save()
            Member.objects.create(clinic=clinic, user=user, role=Member.ADMINISTRATOR)

        client = Client()
        # the sign-in lockout's backend (django-axes) needs a real request; the demo's own client signs in
        # directly after checking the password the pages will take
        user = User.objects.get(username=DEMO_USER)
        if not user.check_password(DEMO_PASSWORD):
            raise CommandError("the demo user cannot log in")
        client.force_login(user, backend="django.contrib.auth.backends.ModelBackend")
        self.say("registering the rig and its test field through the API ...")
        self.api(client, "post", "/api/testfields",
                 json={"clinic": clinic.pk, "testfield": json.loads((scenario / "testfield.json").read_text())})
        key = self.api(client, "post", "/api/rigs", json={
            "clinic": clinic.pk, "rig": json.loads((scenario / "rig.json").read_text())})["key"]

        poses = sorted((scenario / "captures").glob("testfield-pose*"))
        self.say(f"uploading {len(poses)} test-field poses; the last one starts the calibration job ...")
        for folder in poses:
            s = self.upload(client, key, folder, calibration_set="demo", poses=len(poses))
        job = Job.objects.get(uid=s["jobs"][0]["id"])
        if job.state != Job.SUCCEEDED:
            raise CommandError(f"calibration failed: {job.error}")
        calib = job.calibration_result
        rms = [v for v in calib.figures["residual_rms_px"].values() if v is not None]
        self.say(f"  calibrated {len(rms)} cameras: residual RMS {min(rms):.3f}-{max(rms):.3f} px, "
                 f"sigma0 {calib.figures['sigma0']:.2f}")

        patient = self.api(client, "post", "/api/patients", json={
            "clinic": clinic.pk, "identifier": "DEMO-001", "name": "Alex Example", "date_of_birth": "2013-03-14",
            "sex": "F", "notes": "Right thoracic curve, under observation."})
        baseline = self.api(client, "post", f"/api/patients/{patient['id']}/visits",
                            json={"date": "2026-07-20", "reason": "baseline"})
        later = self.api(client, "post", f"/api/patients/{patient['id']}/visits",
                         json={"date": "2026-11-20", "reason": "4-month follow-up"})
        for name, visit, what in (("visit0-a", baseline, "baseline"), ("visit0-b", baseline, "same-day re-scan"),
                                  ("visit1-a", later, "four months later")):
            self.say(f"uploading the {what} ({name}) image by image; the reconstruction job runs ...")
            s = self.upload(client, key, scenario / "captures" / name, visit=visit["id"])
            job = Job.objects.get(uid=s["jobs"][0]["id"])
            if job.state != Job.SUCCEEDED:
                self.say(self.style.WARNING(f"  job {job.state}: {job.error}"))
                continue
            rec = self.mark_what_was_not_found(client, job.reconstruction, scenario / "truth" / name, visit["id"])
            pairs = ", ".join(f"{p['a']}-{p['b']} {p['average_normal_distance_mm']:.3f} mm "
                              f"({p['overlap_matched_fraction']:.0%} of the overlap)"
                              for p in rec.report["registration"]["pairs"]
                              if p["average_normal_distance_mm"] is not None)
            ind = rec.indices or {}
            self.say(f"  torso: {rec.points} points, status {rec.status}; registration {pairs}")
            if ind:
                flat = flatten(ind)
                self.say("  indices: " + "; ".join(
                    f"{labels.label(k)} {labels.size_words(k, flat[k]) if k in flat else 'not measurable'}"
                    for k in ("surface_rotation_deg.max", "lateral_deviation_mm.max", "hump_mm",
                              "trunk_imbalance_mm", "asymmetry_mm")))

        from analysis.repeatability import index_changes

        from clinic.analysis_step import clinic_mdc

        mdc = clinic_mdc(clinic)
        self.say("\nfindings")
        from analysis.repeatability import MIN_REPEAT_PAIRS

        from clinic.analysis_step import repeat_pairs

        self.say(f"  (the demo's reduced rig ({preset} preset) gives torsos {'about 3' if preset == 'demo' else 'about 5'} "
                 "mm between points, sparser than the paper-scale rig's: the figures show\n   the workflow, not the "
                 "scanner's accuracy; see docs/analysis.md for the paper-scale validation)")
        pairs = repeat_pairs(clinic)
        if pairs < MIN_REPEAT_PAIRS:
            self.say(f"  this clinic has {pairs} of the {MIN_REPEAT_PAIRS} same-visit re-scans its own noise verdicts "
                     "need; until then they rest on the scanner's repeatability measured on simulated re-scans")
        for comp in Comparison.objects.filter(later__session__visit__patient_id=patient["id"]).order_by("created"):
            r = comp.report
            kind = "same-visit re-scan (repeatability)" if comp.is_repeat else "follow-up against baseline"
            self.say(f"  {kind}: average normal distance {r['average_normal_distance_mm']:.2f} mm, "
                     f"{r['matched_fraction']:.0%} matched, signed mean {r['signed_distance_mm']['mean']:+.2f} mm")
            changes = index_changes(comp.earlier.indices or {}, comp.later.indices or {}, mdc,
                                    sides_agree=(r.get("facing") or {}).get("consistent", True))
            for k in ("surface_rotation_deg.max", "lateral_deviation_mm.max", "spine_lateral_deviation_mm.max",
                      "hump_mm", "asymmetry_mm"):
                c = changes.get(k)
                if c:
                    flag = ("BEYOND the scanner's noise" if c["exceeds_mdc"] else
                            "within the scanner's noise" if c["exceeds_mdc"] is False else "no verdict yet")
                    unit = labels.unit(k)
                    noise = "" if c["mdc"] is None else f", noise ±{c['mdc']:.1f}{'' if unit == '°' else ' '}{unit}"
                    words = labels.change_texts(k, c)
                    self.say(f"    {labels.label(k)}: {words['from_to'].replace('→', '->')} ({words['change']}"
                             f"{noise}): {flag}")
        n = Reconstruction.objects.filter(session__visit__patient_id=patient["id"]).count()
        self.say(f"\n{n} torsos reconstructed in {time.perf_counter() - t0:.0f} s in all.")
        self.say("Open the clinicians' pages:\n"
                 "  DEBUG=true .venv/bin/python manage.py runserver\n"
                 f"  http://127.0.0.1:8000/  user {DEMO_USER!r}, password {DEMO_PASSWORD!r}")
