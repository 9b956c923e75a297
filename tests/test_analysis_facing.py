"""The patient's left and right: from the rig's footplate, or from shape evidence that noise and crops cannot flip.

A scan cut from the waist to the head made the old profile rule take the front for the back (the patient's
sides swapped); the midline-sagitta cue and the rig's footplate must not.
"""

import numpy as np
import pytest

from analysis.compare import compare_torsos
from analysis.frame import detect_posterior
from analysis.indices import analyse_torso
from analysis.synthetic import scan_surface
from analysis.torso import Torso, read_torso
from recon_engine.simulator.bodies import Posture, load_makehuman, pose_body
from recon_engine.simulator.config import SubjectConfig
from recon_engine.simulator.rig import rotation_about


@pytest.fixture(scope="module")
def body():
    return load_makehuman(1550.0, subdivisions=1)


def scan(body, yaw_deg=0.0, crop="torso", seed=0, rotation_deg=0.0, n=30_000):
    """A scan of the MakeHuman subject turned by ``yaw_deg`` (its back towards the yaw's +Y), and its true posterior."""
    R = rotation_about([0, 0, 1], yaw_deg)
    V, _ = pose_body(body, SubjectConfig(), Posture(rotation_deg, 0.4 * rotation_deg, 0.0, 0.0, R, np.zeros(3)))
    z = V[body.triangles].mean(axis=1)[:, 2]
    region = {"torso": body.torso_faces,
              "waist-to-head": z > body.z_sacrum + 60,
              "hips-to-chin": (z > body.z_sacrum - 60) & (z < body.z_c7 + 160)}[crop]
    return scan_surface(V, body.triangles, region, n_points=n, seed=seed), R @ np.array([0.0, 1.0, 0.0])


@pytest.mark.parametrize("crop,yaw", [("waist-to-head", 0.0), ("waist-to-head", 123.0), ("hips-to-chin", 211.0)])
def test_it_finds_the_back_whatever_the_crop(body, crop, yaw):
    torso, truth = scan(body, yaw, crop)
    post, info = detect_posterior(torso.points)
    assert np.degrees(np.arccos(np.clip(post @ truth, -1, 1))) < 10
    assert info["status"] == "certain" and info["method"] == "shape"


def test_the_rig_footplate_decides_and_the_shape_checks_it(body):
    torso, truth = scan(body, 37.0)
    post, info = detect_posterior(torso.points, prior={"posterior": truth.tolist(), "back_towards": ["A", "B"]})
    assert post @ truth > 0.98 and info["method"] == "rig" and info["status"] == "certain" and info["shape_agrees"]
    # the patient stood the other way round: the rig and the shape disagree, and the scan says so
    post, info = detect_posterior(torso.points, prior={"posterior": (-truth).tolist(), "back_towards": ["C", "D"]})
    assert info["status"] == "uncertain" and "other way round" in info["reason"]


def test_an_uncertain_facing_withholds_every_sided_index(body):
    torso, truth = scan(body, 0.0, rotation_deg=8.0)
    torso.patient = {"posterior": (-truth).tolist(), "back_towards": ["C", "D"], "source": "rig"}
    rep = analyse_torso(torso).report
    assert rep["frame"]["facing"]["status"] == "uncertain"
    assert rep["surface_rotation_deg"]["max"] is None and rep["hump_mm"] is None
    assert rep["trunk_imbalance_mm"] is None and "facing is uncertain" in rep["not_measurable"]["reason"]
    assert rep["trunk_length_mm"] > 300  # what does not depend on the sides is still measured


def marked_as_asked(body, torso, posterior):
    """The report, with the trunk landmarks marked as a clinician would where the analysis asks for them: the
    back's most posterior skin point at the sacrum's (C7's) height, within 20 mm of the back's middle."""
    rep = analyse_torso(torso).report
    asked = [n for n in ("sacral_point", "vertebra_prominens") if n in (rep.get("not_measurable") or {}).get("mark", [])]
    if not asked:
        return rep
    # the C7 crop ends at the joint: VP is clicked just below it
    marks = {n: clicked(torso, body.z_sacrum if n == "sacral_point" else body.z_c7 - 5.0, posterior).tolist()
             for n in asked}
    return analyse_torso(torso, landmarks=marks).report


def clicked(torso, z, posterior):
    """A clinician's click on the back at height ``z`` (mm): the most posterior skin point there within 20 mm of
    the back's middle; ``posterior`` is the back's direction (rig frame)."""
    P = torso.points[np.abs(torso.points[:, 2] - z) < 4.0]
    across = np.cross([0.0, 0.0, 1.0], posterior) @ P.T
    P = P[np.abs(across - np.median(across)) < 20.0]
    return P[np.argmax(P @ posterior)]


def test_same_day_rescans_keep_the_patients_sides(body):
    # the re-scan is cut differently (the neck and chin in view) and sampled anew: the sides must not swap.
    # The "torso" crop stops 30 mm below the sacrum. In the frame with the pelvis's yaw the midline's depth
    # falls from the crop's lowest row (no sacral crest; in the frame 0.7 deg off, a 20 mm plateau was one),
    # so the analysis asks for SP, and it is marked as a clinician would; so is VP, whose neck is cut off
    a, truth = scan(body, 15.0, "torso", seed=1, rotation_deg=8.0)
    b, _ = scan(body, 15.0, "hips-to-chin", seed=2, rotation_deg=8.0)
    ra, rb = (marked_as_asked(body, t, truth) for t in (a, b))
    for rep in (ra, rb):
        assert rep["frame"]["facing"]["status"] == "certain"
        assert np.asarray(rep["frame"]["posterior"]) @ truth > 0.95
    # the right back comes backwards in both (positive surface rotation), never one side in one and the other
    assert ra["surface_rotation_deg"]["max"] > 2 and rb["surface_rotation_deg"]["max"] > 2


def test_the_facing_travels_in_the_torso_file(tmp_path, body):
    from recon_engine.results import posterior_comment
    from recon_engine.surface import write_ply

    torso, truth = scan(body, 0.0, n=5000)
    write_ply(tmp_path / "torso.ply", torso.points, torso.normals, comments=["torsoscan torso",
              posterior_comment(truth, ("A", "B"))])
    back = read_torso(tmp_path / "torso.ply")
    assert back.patient["back_towards"] == ["A", "B"] and np.allclose(back.patient["posterior"], truth, atol=1e-5)


def test_it_does_not_compare_sides_when_two_scans_disagree_on_the_facing(body):
    a, truth = scan(body, 0.0, seed=1, rotation_deg=8.0)
    b, _ = scan(body, 0.0, seed=2, rotation_deg=8.0)
    b = Torso(b.points, b.normals, source="turned", patient={"posterior": (-truth).tolist(), "source": "rig"})
    rep = compare_torsos(a, b)["report"]
    assert rep["facing"]["consistent"] is False and "disagree" in rep["facing"]["reason"]
    from analysis.repeatability import index_changes

    ch = index_changes({"surface_rotation_deg": {"max": 5.0}, "trunk_length_mm": 500.0},
                       {"surface_rotation_deg": {"max": -5.0}, "trunk_length_mm": 501.0},
                       sides_agree=rep["facing"]["consistent"])
    assert set(ch) == {"trunk_length_mm"}
