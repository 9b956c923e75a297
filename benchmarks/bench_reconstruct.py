"""Benchmark: the whole torso end to end at paper scale (our calibration, arms displaced).

    .venv/bin/python benchmarks/bench_reconstruct.py --scenario bench-out/paper --capture visit0-a \
        --calibration bench-out/paper-calibration.json

Several captures (``--capture visit0-a visit0-b visit1-a``) give the
displacement errors of 3 arms each, and their means per method: one capture's
three arms are too few to rank registrations that differ by micrometres.

``--calibration`` is our own calibration from the scenario's raw test-field
images (``bench_calibrate.py`` or ``torsoscan calibrate`` writes it). The
torso capture's arms B, C, D are displaced from their calibrated placement;
ICPatch brings them back. Figures: distance of the fused torso points to the
true body (RMS, 95th percentile, max), coverage of the torso area that two
cameras of one arm see, the paper's Table 1 (average normal distance and
matched fraction of every neighbouring pair after the multiple
registration), the misclosure that pair-wise registration alone leaves at the
closing pair, and the time of each stage. Writes
``--json`` (default ``bench-out/bench_reconstruct.json``; and each capture's arm surfaces, pickled,
with ``--keep-surfaces``).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from recon_engine.o3d import o3d  # noqa: E402

from recon_engine.formats import read_calibration, read_capture, read_rig  # noqa: E402
from recon_engine.parallel import return_freed_images  # noqa: E402
from recon_engine.reconstruction import TorsoConfig, reconstruct_torso, register_arms  # noqa: E402
from recon_engine.registration import ICPatchConfig, Transform, pair_fit  # noqa: E402
from recon_engine.surface import in_patches  # noqa: E402

from bench_reconstruct_arm import Truth  # noqa: E402
from provenance import provenance  # noqa: E402


def displacement_errors(T: dict, D: dict, at: np.ndarray) -> dict:
    """Per arm: rotation error (deg) and RMS position error (mm) of the recovered displacement over ``at``."""
    out = {}
    for a, Ta in T.items():
        dR = Ta.R @ D[a].R.T
        ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        x = D[a].inverse().apply(at)
        err = Ta.apply(x) - at
        out[a] = {"rotation_deg": ang, "rms_mm": float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
                  "scale": float(Ta.scale)}
    return out


def point_cloud(surface):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface.points))
    pcd.normals = o3d.utility.Vector3dVector(surface.normals)
    return pcd


def _icp(src, dst, init):
    """Point-to-plane ICP, coarse to fine as a careful user runs it (the same 25 mm start as ours, down to 0.5 mm)."""
    reg = o3d.pipelines.registration
    M = init
    for dist in (25.0, 10.0, 5.0, 2.0, 1.0, 0.5):
        M = reg.registration_icp(src, dst, dist, M, reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(max_iteration=60)).transformation
    return M


def _from_matrix(M):
    return Transform(1.0, np.asarray(M[:3, :3]), np.asarray(M[:3, 3]))


def open3d_pairwise(surfaces, order):
    """Open3D point-to-plane ICP chained from the reference arm."""
    pc = {a: point_cloud(surfaces[a]) for a in order}
    M = {order[0]: np.eye(4)}
    for prev, a in zip(order[:-1], order[1:]):
        M[a] = M[prev] @ _icp(pc[a], pc[prev], np.eye(4))
    return {a: _from_matrix(m) for a, m in M.items()}


def open3d_multiway(surfaces, order):
    """Open3D's multiway registration: pose graph of neighbouring ICP edges, the loop closed, optimized."""
    reg = o3d.pipelines.registration
    pc = {a: point_cloud(surfaces[a]) for a in order}
    graph = reg.PoseGraph()
    odo = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odo))
    n = len(order)
    for i in range(n):
        j = (i + 1) % n
        # edge: node j's surface into node i's frame
        M = _icp(pc[order[j]], pc[order[i]], np.eye(4) if j else np.linalg.inv(odo))
        info = reg.get_information_matrix_from_point_clouds(pc[order[j]], pc[order[i]], 1.0, M)
        # Open3D's convention: an edge (source, target, T) with T mapping source into target
        if j:
            odo = odo @ M
            graph.nodes.append(reg.PoseGraphNode(odo))  # node pose: node frame -> reference frame
            graph.edges.append(reg.PoseGraphEdge(j, i, M, info, uncertain=False))
        else:
            graph.edges.append(reg.PoseGraphEdge(0, i, M, info, uncertain=True))
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(),
                            reg.GlobalOptimizationOption(max_correspondence_distance=1.0, edge_prune_threshold=0.25,
                                                         reference_node=0))
    return {a: _from_matrix(graph.nodes[k].pose) for k, a in enumerate(order)}


def kept_surfaces_path(scenario: str, capture: str) -> str:
    """Where ``--keep-surfaces`` pickles a capture's arm surfaces: one file per scenario and capture."""
    return f"bench-out/surfaces-{Path(scenario).name}-{capture}.pkl"


def run_capture(args, capture: str) -> dict:
    """Reconstruct one capture end to end and register its surfaces with every method: its figures."""
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    cal = read_calibration(args.calibration)
    cap = read_capture(S / "captures" / capture, rig)
    t0 = time.perf_counter()
    res = reconstruct_torso(cap, rig, cal, args.torso_cfg, progress=lambda m: print(f"  {m}", flush=True))
    wall = time.perf_counter() - t0
    truth = Truth(S, capture)
    true_cal = read_calibration(S / "truth" / capture / "calibration.json")
    P = res["points"]
    d = truth.distance(P)
    # torso area that two cameras of one arm see (matching happens inside an arm)
    seen2 = np.zeros(len(truth.area), bool)
    for arm in rig.arms:
        seen = np.sum([truth.seen(true_cal.cameras[c]) for c in arm.cameras], axis=0)
        seen2 |= seen >= 2
    near, _ = cKDTree(P).query(truth.centroid[seen2], k=1, distance_upper_bound=2.0)
    covered = np.isfinite(near)
    coverage = float(truth.area[seen2][covered].sum() / truth.area[seen2].sum())
    rep = res["report"]
    reg = rep["registration"]
    out = {
        "capture": capture, "reference": rig.reference_arm.id,
        "ours_settings": {"fill_spacing_mm": args.torso_cfg.arm.tracking.fill_spacing_mm,
                          "max_sigma_factor": args.torso_cfg.arm.max_sigma_factor,
                          "local_quadric_neighbours": args.torso_cfg.arm.local_quadric_neighbours,
                          "obliquity_bias": args.torso_cfg.arm.obliquity_bias},
        "points": int(len(P)), "rms_mm": float(np.sqrt(np.mean(d ** 2))), "p95_mm": float(np.percentile(d, 95)),
        "max_mm": float(d.max()), "coverage": coverage, "seen_area_cm2": float(truth.area[seen2].sum() / 100),
        "table1": reg["pairs"], "pairwise": reg["pairwise"], "sigmas": reg["sigmas"],
        "closing_pair_after_pairwise_only": reg["closing_pair_after_pairwise_only"],
        "seconds": {**rep["seconds"], "wall": wall},
        "arm_seconds": {a: r["seconds"]["total"] for a, r in rep["arms"].items()},
    }
    # each arm's recovered displacement against the truth, ours and Open3D's
    disp = json.loads((S / "truth" / capture / "truth.json").read_text())["arm_displacements"]
    D = {a: Transform(1.0, np.array(v["R"]), np.array(v["t"])) for a, v in disp.items()}
    out["displacement_error"] = {"ours": displacement_errors(res["transforms"], D, truth.centroid)}
    # the peers register what ours registers: the points in the arms' patches (the flanks' points are fused only)
    surfaces = {a: in_patches(s) for a, s in res["surfaces"].items()}
    order = [a.id for a in rig.arms if a.id in surfaces]
    for name, fn in (("open3d_icp_pairwise", open3d_pairwise), ("open3d_multiway", open3d_multiway)):
        t1 = time.perf_counter()
        T = fn(surfaces, order)
        dt = time.perf_counter() - t1
        fits = [{"a": a, "b": b, **pair_fit(surfaces[a], surfaces[b], T[a], T[b])}
                for a, b in zip(order, order[1:] + order[:1])]
        out["displacement_error"][name] = displacement_errors(T, D, truth.centroid)
        out.setdefault("peers", {})[name] = {"seconds": dt, "pairs": fits}
    ours_fits = [{"a": a, "b": b, **pair_fit(surfaces[a], surfaces[b], res["transforms"][a], res["transforms"][b])}
                 for a, b in zip(order, order[1:] + order[:1])]
    out.setdefault("peers", {})["ours"] = {"seconds": rep["seconds"]["registration"], "pairs": ours_fits,
                                           "max_patch_edge": ICPatchConfig().max_patch_edge}
    out["status"], out["problems"], out["warnings"] = rep["status"], rep["problems"], rep["warnings"]
    out["strength"] = reg.get("strength", {})
    out["patches"] = {f"{p['a']}-{p['b']}": p.get("patches") for p in reg["pairs"]}
    # our registration again on the same surfaces with the compact-patch filter set otherwise, and with the
    # flat patches, one direction and 20 000 points per pair of the earlier default
    variants = [(f"ours_max_patch_edge_{e}", ICPatchConfig(max_patch_edge=e))
                for e in (None if x.lower() == "none" else float(x) for x in args.patch_edge)
                if e != ICPatchConfig().max_patch_edge]
    variants.append(("ours_flat_patches_one_way_20000",
                     ICPatchConfig(curved_patches=False, symmetric=False, max_points_per_pair=20000)))
    for name, icfg in variants:
        t1 = time.perf_counter()
        alt = register_arms(surfaces, rep["arms"], rep["failed_arms"], rig, cal, replace(args.torso_cfg, icpatch=icfg))
        dt = time.perf_counter() - t1
        areg = alt["report"]["registration"]
        out["displacement_error"][name] = displacement_errors(alt["transforms"], D, truth.centroid)
        out["peers"][name] = {
            "seconds": alt["report"]["seconds"]["registration"], "with_fusion_and_mesh": dt,
            "status": alt["report"]["status"], "strength": areg.get("strength", {}),
            "patches": {f"{p['a']}-{p['b']}": p.get("patches") for p in areg["pairs"]},
            "pairs": [{"a": a, "b": b, **pair_fit(surfaces[a], surfaces[b], alt["transforms"][a], alt["transforms"][b])}
                      for a, b in zip(order, order[1:] + order[:1])]}
    if args.keep_surfaces:
        Path("bench-out").mkdir(exist_ok=True)
        with open(kept_surfaces_path(args.scenario, capture), "wb") as f:
            pickle.dump({"surfaces": surfaces, "reports": rep["arms"], "failed": rep["failed_arms"]}, f)
    print(capture, json.dumps({k: v for k, v in out.items() if k not in ("pairwise", "sigmas", "strength")},
                              indent=1, default=float), flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", nargs="+", default=["visit0-a"])
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json")
    ap.add_argument("--patch-edge", nargs="*", default=["none", "1.75"],
                    help="also register the same surfaces with these ICPatchConfig.max_patch_edge values "
                         "(\"none\": all patches); the default's is not repeated")
    ap.add_argument("--keep-surfaces", action="store_true",
                    help="pickle each capture's arm surfaces and reports to bench-out/surfaces-<scenario>-<capture>.pkl")
    ap.add_argument("--fill-spacing-mm", type=float, default=None,
                    help="our TrackingConfig.fill_spacing_mm (a cheaper rig: 2.0; default: the engine's)")
    ap.add_argument("--max-sigma-factor", type=float, default=None,
                    help="our ReconstructionConfig.max_sigma_factor (with the fill: 4.0; default: the engine's)")
    ap.add_argument("--no-refinement", action="store_true",
                    help="the arms' points as intersected (ReconstructionConfig.local_quadric_neighbours 0)")
    ap.add_argument("--obliquity-bias", type=float, default=None,
                    help="our ReconstructionConfig.obliquity_bias (1/mm; 0: the obliquity bias left in; default: the engine's)")
    ap.add_argument("--json", default="bench-out/bench_reconstruct.json")
    args = ap.parse_args()
    arm = TorsoConfig().arm
    if args.obliquity_bias is not None:
        arm = replace(arm, obliquity_bias=args.obliquity_bias)
    if args.no_refinement:
        arm = replace(arm, local_quadric_neighbours=0)
    if args.fill_spacing_mm is not None:
        arm = replace(arm, tracking=replace(arm.tracking, fill_spacing_mm=args.fill_spacing_mm))
    if args.max_sigma_factor is not None:
        arm = replace(arm, max_sigma_factor=args.max_sigma_factor)
    args.torso_cfg = TorsoConfig(arm=arm)
    return_freed_images()  # as `torsoscan reconstruct` does: the figures are the command's
    run = provenance(__file__)
    runs = {c: run_capture(args, c) for c in args.capture}
    # per method: the mean over every displaced arm of every capture
    methods = list(next(iter(runs.values()))["displacement_error"])
    summary = {}
    for m in methods:
        rows = [e for r in runs.values() for a, e in r["displacement_error"][m].items()
                if a != r["reference"]]
        summary[m] = {"arms": len(rows),
                      "mean_rms_mm": float(np.mean([e["rms_mm"] for e in rows])),
                      "max_rms_mm": float(np.max([e["rms_mm"] for e in rows])),
                      "mean_rotation_deg": float(np.mean([e["rotation_deg"] for e in rows])),
                      "max_rotation_deg": float(np.max([e["rotation_deg"] for e in rows])),
                      "seconds_mean": float(np.mean([r["peers"][m]["seconds"] if m in r["peers"] else
                                                     r["peers"]["ours"]["seconds"] for r in runs.values()]))}
    out = {**run, "captures": runs, "summary": summary}
    if len(runs) == 1:
        out.update(next(iter(runs.values())))  # the single-capture layout of earlier runs
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
