"""Benchmark: registration alone, on arm surfaces kept by ``bench_reconstruct.py --keep-surfaces``.

    .venv/bin/python benchmarks/bench_reconstruct.py --capture visit0-a visit0-b visit1-a --keep-surfaces
    .venv/bin/python benchmarks/bench_registration.py --capture visit0-a visit0-b visit1-a  # reads bench-out/surfaces-<scenario>-<capture>.pkl

The same four surfaces of each capture are registered by our ICPatch (the
default configuration and the variants below) and by Open3D's pair-wise ICP
and multiway registration, and each arm's recovered displacement is compared
with the simulator's truth: the RMS position error over the torso's true
surface (mm) and the rotation error (deg). Reconstruction is not repeated, so
registration settings can be compared in seconds on exactly the same data.
Writes ``bench-out/bench_registration.json``.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from recon_engine.o3d import o3d  # noqa: E402

from recon_engine.formats import read_calibration, read_rig  # noqa: E402
from recon_engine.reconstruction import TorsoConfig, register_arms  # noqa: E402
from recon_engine.registration import Transform, choose_patches, icpatch, patch_indices  # noqa: E402

from bench_reconstruct import kept_surfaces_path, point_cloud, displacement_errors, open3d_multiway, open3d_pairwise  # noqa: E402
from bench_reconstruct_arm import Truth  # noqa: E402
from provenance import provenance  # noqa: E402

# our registration's variants: name -> changes to the default ICPatchConfig
VARIANTS = {
    "ours": {},
    "ours_rigid": {"estimate_scale": False},
    "ours_free_scale": {"estimate_scale": True},
    "ours_rigid_one_way": {"estimate_scale": False, "symmetric": False},
    "ours_no_rim_margin": {"rim_margin_mm": None},
    "ours_rim_margin_3": {"rim_margin_mm": 3.0},
    "ours_rim_margin_7": {"rim_margin_mm": 7.0},
    "ours_rim_margin_10": {"rim_margin_mm": 10.0},
    "ours_all_points": {"max_points_per_pair": None},
    "ours_all_patches": {"max_patch_edge": None},
    "ours_min_distance_0.3": {"min_distance_mm": 0.3},
    "ours_flat_patches": {"curved_patches": False},
    "ours_rim_margin_1": {"rim_margin_mm": 1.0},
    "ours_rim_margin_2": {"rim_margin_mm": 2.0},
    "ours_rim_margin_0.6": {"rim_margin_mm": 0.6},
    "ours_rim_margin_1.7": {"rim_margin_mm": 1.7},
    "ours_no_rim_margin_all_patches": {"rim_margin_mm": None, "max_patch_edge": None},
    "ours_no_rim_margin_flat_patches": {"rim_margin_mm": None, "curved_patches": False},
}
# precision weights (weighted), a scale prior (scale_sigma) and each pair's error as a nuisance (pair_sigma,
# pair_stiffness) were measured here and left the engine (docs/benchmarks.md, fifth session; git history); so was a
# rim margin of 9 mm * g^2 (at most 5 mm; 20123e5, reverted: docs/benchmarks.md, "Registration alone")
DEFAULT_VARIANTS = ["ours", "ours_free_scale"]


def icpatch_edges(surfaces, order, cfg):
    """Pair-wise ICPatch of every neighbouring pair from the nominal placement: ``{(j, i): Transform}``, arm
    ``order[j]``'s surface into ``order[i]``'s frame, for ``j = i + 1`` around the circle."""
    indices = patch_indices(surfaces, cfg)
    out = {}
    for i in range(len(order)):
        j = (i + 1) % len(order)
        a, b = order[j], order[i]
        index, _ = choose_patches(surfaces[a].points, surfaces[a].normals, indices[b], Transform.identity(),
                                  cfg.initial_distance_mm, cfg)
        out[(j, i)] = icpatch(surfaces[a], surfaces[b], Transform.identity(), cfg, index=index)["transform"]
    return out


def pose_graph(surfaces, order, edges):
    """Open3D's pose graph optimisation (as in ``open3d_multiway``) over the given rigid edges."""
    reg = o3d.pipelines.registration
    pc = {a: point_cloud(surfaces[a]) for a in order}
    graph = reg.PoseGraph()
    odo = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odo))
    for (j, i), T in sorted(edges.items(), key=lambda e: e[0][1]):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = T.R, T.t
        info = reg.get_information_matrix_from_point_clouds(pc[order[j]], pc[order[i]], 1.0, M)
        if j:
            odo = odo @ M
            graph.nodes.append(reg.PoseGraphNode(odo))
        graph.edges.append(reg.PoseGraphEdge(j, i, M, info, uncertain=j == 0))
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(),
                            reg.GlobalOptimizationOption(max_correspondence_distance=1.0, edge_prune_threshold=0.25,
                                                         reference_node=0))
    return {a: Transform(1.0, np.asarray(graph.nodes[k].pose[:3, :3]), np.asarray(graph.nodes[k].pose[:3, 3]))
            for k, a in enumerate(order)}


def edge_errors(edges, order, D, at):
    """RMS error (mm) over the torso ``at`` of each pair-wise edge against the true relative displacement."""
    out = {}
    for (j, i), T in edges.items():
        xj = D[order[j]].inverse().apply(at)
        err = T.apply(xj) - D[order[i]].inverse().apply(at)
        out[f"{order[j]}->{order[i]}"] = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", nargs="+", default=["visit0-a", "visit0-b", "visit1-a"])
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json")
    ap.add_argument("--variant", nargs="*", default=DEFAULT_VARIANTS, choices=list(VARIANTS))
    args = ap.parse_args()
    run = provenance(__file__)
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    cal = read_calibration(args.calibration)
    base = TorsoConfig().icpatch
    rows = {}
    for capture in args.capture:
        with open(kept_surfaces_path(args.scenario, capture), "rb") as f:
            kept = pickle.load(f)
        surfaces, reports, failed = kept["surfaces"], kept["reports"], kept["failed"]
        truth = Truth(S, capture)
        disp = json.loads((S / "truth" / capture / "truth.json").read_text())["arm_displacements"]
        D = {a: Transform(1.0, np.array(v["R"]), np.array(v["t"])) for a, v in disp.items()}
        order = [a.id for a in rig.arms if a.id in surfaces]
        runs = {}
        for name in args.variant:
            icfg = replace(base, **VARIANTS[name])
            res = register_arms(surfaces, reports, failed, rig, cal, TorsoConfig(icpatch=icfg))
            runs[name] = {"errors": displacement_errors(res["transforms"], D, truth.centroid),
                          "seconds": res["report"]["seconds"]["registration"], "status": res["report"]["status"],
                          "table1": [(p["a"], p["b"], p["average_normal_distance_mm"])
                                     for p in res["report"]["registration"]["pairs"]]}
        # diagnostic: our rigid pair-wise ICPatch edges, spread around the loop by Open3D's pose graph instead of
        # our simultaneous adjustment (which registration's loop closure lands nearer the truth)
        t0 = time.perf_counter()
        edges = icpatch_edges(surfaces, order, replace(base, estimate_scale=False))
        runs["icpatch_rigid_edges_open3d_pose_graph"] = {
            "errors": displacement_errors(pose_graph(surfaces, order, edges), D, truth.centroid),
            "seconds": time.perf_counter() - t0, "edge_errors": edge_errors(edges, order, D, truth.centroid)}
        for name, fn in (("open3d_icp_pairwise", open3d_pairwise), ("open3d_multiway", open3d_multiway)):
            t0 = time.perf_counter()
            T = fn(surfaces, order)
            runs[name] = {"errors": displacement_errors(T, D, truth.centroid), "seconds": time.perf_counter() - t0}
        for name, r in runs.items():
            errs = {a: round(e["rms_mm"], 4) for a, e in r["errors"].items() if a != rig.reference_arm.id}
            print(f"{capture} {name:24s} {errs} {r['seconds']:.1f} s", flush=True)
            if "edge_errors" in r:
                print(f"{capture} pair-wise ICPatch (rigid) edges against the truth: "
                      + ", ".join(f"{k} {v:.4f} mm" for k, v in r["edge_errors"].items()), flush=True)
        rows[capture] = runs
    summary = {}
    for name in next(iter(rows.values())):
        e = [v for runs in rows.values() for a, v in runs[name]["errors"].items() if a != rig.reference_arm.id]
        summary[name] = {"arms": len(e), "mean_rms_mm": float(np.mean([x["rms_mm"] for x in e])),
                         "max_rms_mm": float(np.max([x["rms_mm"] for x in e])),
                         "mean_rotation_deg": float(np.mean([x["rotation_deg"] for x in e])),
                         "seconds_mean": float(np.mean([runs[name]["seconds"] for runs in rows.values()]))}
        print(f"{name:24s} mean {summary[name]['mean_rms_mm']:.4f} mm, max {summary[name]['max_rms_mm']:.4f} mm, "
              f"{summary[name]['mean_rotation_deg']:.4f} deg, {summary[name]['seconds_mean']:.1f} s")
    Path("bench-out/bench_registration.json").write_text(json.dumps(
        {**run, "captures": rows, "summary": summary}, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
