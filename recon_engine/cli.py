"""The engine's commands of ``torsoscan``: thin commands that call the engine's stages.

``simulate``, ``calibrate``, ``stability``, ``reconstruct`` and
``reconstruct-arm``. The installed ``torsoscan`` (:mod:`analysis.cli`) adds
the analysis commands (``compare``, ``indices``) to these; imports run one
way, ``analysis`` on ``recon_engine``, so this module never imports
``analysis``. ``python -m recon_engine.cli`` runs the engine's commands alone.

Exit status 0 on success; non-zero with a message on standard error that
names the file and the problem otherwise (capture-format spec, section 6).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from .formats import FormatError
from .simulator.config import PRESETS


def _cmd_simulate(args) -> int:
    from .simulator.config import preset
    from .simulator.scenario import simulate

    changes = []
    for text in args.lens_change or []:
        try:
            cam, rest = text.split(":", 1)
            what, amount = rest.split("=", 1)
            changes.append((cam, what, float(amount)))
        except ValueError:
            raise ValueError(f"--lens-change {text!r}: expected CAMERA:WHAT=AMOUNT, e.g. A3:pd=0.001") from None
    cfg = preset(args.preset, seed=args.seed, session=args.session, lens_changes=tuple(changes))
    subject = cfg.subject
    changes = {k: v for k, v in {
        "torso": args.torso, "curve": args.curve, "rotation_deg": args.rotation,
        "lateral_mm": args.lateral, "progression_deg": args.progression}.items() if v is not None}
    if changes:
        cfg = replace(cfg, subject=replace(subject, **changes))
    print(f"simulating preset {cfg.preset!r} (seed {cfg.seed}, {cfg.subject.torso} torso, "
          f"{cfg.subject.curve} curve, {cfg.subject.rotation_deg:g} deg) into {args.out}")
    summary = simulate(args.out, cfg, force=args.force)
    out = Path(args.out)
    print("wrote:")
    for rel in ["rig.json", "testfield.json", *summary["captures"], "truth/"]:
        print(f"  {out / rel}")
    print(f"in {summary['timings_s']['total']:.1f} s")
    return 0


def _cmd_calibrate(args) -> int:
    from .calibration import calibrate
    from .formats import read_capture, read_rig, read_testfield, write_calibration, write_json

    rig = read_rig(args.rig)
    testfield = read_testfield(args.testfield)
    captures = [read_capture(c, rig) for c in args.captures]
    calib, report = calibrate(captures, rig, testfield, progress=lambda m: print(f"  {m}", flush=True))
    write_calibration(args.out, calib)
    print(f"calibrated {len(calib.cameras)} of {len(rig.camera_ids)} cameras from {len(captures)} pose(s); "
          f"sigma0 {report.sigma0:.2f}, {report.observations} corner coordinates, "
          f"{100 * (1 - report.inlier_fraction):.2f}% rejected")
    rms = [v for v in report.residual_rms_px.values() if v is not None]
    print(f"residual RMS per camera: median {np.median(rms):.3f} px, max {np.max(rms):.3f} px")
    if report.dropped:
        print("targets dropped: " + ", ".join(f"{k} {v}" for k, v in sorted(report.dropped.items())))
    for cam_id, why in report.failed_cameras.items():
        print(f"camera {cam_id} not calibrated: {why}", file=sys.stderr)
    for w in report.warnings[:10]:
        print(f"warning: {w}")
    if len(report.warnings) > 10:
        print(f"... and {len(report.warnings) - 10} more warnings (in {args.out})")
    if args.report:
        write_json(args.report, report.to_dict())
    print(f"wrote {args.out}")
    return 0


def _cmd_stability(args) -> int:
    from .formats import read_calibration, write_json
    from .stability import compare_calibrations

    a, b = read_calibration(args.calibration_a), read_calibration(args.calibration_b)
    result = compare_calibrations(a, b, threshold_px=args.threshold, criterion=args.criterion)
    write_json(args.out, result)
    for cam_id, m in result["cameras"].items():
        verdict = {True: "stable", False: "UNSTABLE", None: "not judged"}[m["stable"]]
        t = m["threshold_px"]
        arm = f", ARM {m['arm_px']:.3f}/{t['arm_px']:.2f} px" if "arm_px" in m else ""
        print(f"{cam_id}: ZROT {m['zrot_px']:.3f}/{t['zrot_px']:.2f} px, ROT {m['rot_px']:.3f}/{t['rot_px']:.2f} px, "
              f"SPR {m['spr_px']:.3f}/{t['spr_px']:.2f} px{arm} (measure/threshold) {verdict}")
    print(f"wrote {args.out}")
    return 0


DESCRIPTION = "The torsoscan command line: thin commands that call the engine's and the analysis' stages."


def add_commands(sub) -> None:
    """Add the engine's commands to ``sub`` (an ``argparse`` subparsers action); each sets ``func``."""
    p = sub.add_parser("simulate", help="render a complete simulated scenario with its ground truth")
    p.add_argument("--preset", choices=list(PRESETS), default="tiny",
                   help="tiny: 480x320 px images for tests; demo: 720x480 (make demo); cheap: 1000x667 (a cheaper "
                        "rig's cameras); paper: the paper's 3000x2000 px rig")
    p.add_argument("--out", required=True, help="scenario folder to write")
    p.add_argument("--seed", type=int, default=0, help="the installation: rig, lenses, test field, patient")
    p.add_argument("--session", type=int, default=0,
                   help="what differs between sessions of one installation: poses, arm swings, posture, noise")
    p.add_argument("--lens-change", action="append", metavar="CAM:WHAT=AMOUNT",
                   help="disturb a lens since installation: pd (relative), pp_x, pp_y (px) or k1; repeatable")
    p.add_argument("--torso", choices=["makehuman", "parametric"])
    p.add_argument("--curve", choices=["C", "S"], help="scoliotic curve pattern")
    p.add_argument("--rotation", type=float, help="axial rotation at the main apex (deg)")
    p.add_argument("--lateral", type=float, help="lateral deviation at the main apex (mm)")
    p.add_argument("--progression", type=float, help="rotation added at the later visit (deg)")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("calibrate", help="calibrate the rig's cameras from test-field captures")
    p.add_argument("--rig", required=True)
    p.add_argument("--testfield", required=True)
    p.add_argument("--out", required=True, help="calibration.json to write")
    p.add_argument("--report", help="also write the detailed report (dropped targets, residuals) here")
    p.add_argument("captures", nargs="+", metavar="CAPTURE", help="test-field capture bundles (folders or .zip)")
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("stability", help="compare two calibrations camera by camera (ZROT, ROT, SPR, ARM)")
    p.add_argument("--out", required=True)
    p.add_argument("--threshold", type=float, help="px; default from the calibrations' own residuals")
    p.add_argument("--criterion", choices=["all", "zrot", "rot", "spr", "arm"], default="all",
                   help="the measure(s) that decide the verdict (default: unstable when any exceeds its threshold)")
    p.add_argument("calibration_a", metavar="CALIBRATION_A.json")
    p.add_argument("calibration_b", metavar="CALIBRATION_B.json")
    p.set_defaults(func=_cmd_stability)

    p = sub.add_parser("reconstruct", help="the torso from one torso capture: all arms, ICPatch, fusion")
    p.add_argument("--rig", required=True)
    p.add_argument("--calibration", required=True)
    p.add_argument("--out", required=True, help="folder for torso.ply, torso-mesh.ply and report.json")
    p.add_argument("--force", action="store_true", help="write into OUT even if it holds files")
    p.add_argument("--arm-workers", type=int, default=0, metavar="N",
                   help="arms reconstructed at once, each on its own thread with its share of the cores (default 0: "
                        "one per core); 1 reconstructs them one after the other with every core (docs/benchmarks.md, "
                        "the whole visit)")
    p.add_argument("capture", metavar="CAPTURE", help="torso capture bundle (folder or .zip)")
    p.set_defaults(func=_cmd_reconstruct)

    p = sub.add_parser("reconstruct-arm", help="the point surface one arm sees in a torso capture")
    p.add_argument("--rig", required=True)
    p.add_argument("--calibration", required=True)
    p.add_argument("--arm", required=True, help="arm id, e.g. A")
    p.add_argument("--out", required=True, help="PLY to write (points, normals, patches, sigma_mm, rays)")
    p.add_argument("--report", help="report JSON (default: OUT with .json)")
    p.add_argument("capture", metavar="CAPTURE", help="torso capture bundle (folder or .zip)")
    p.set_defaults(func=_cmd_reconstruct_arm)


def build_parser() -> argparse.ArgumentParser:
    """The engine's commands alone."""
    parser = argparse.ArgumentParser(prog="torsoscan", description="The engine's commands of torsoscan (the "
                                     "installed torsoscan, analysis.cli, adds compare and indices).")
    add_commands(parser.add_subparsers(dest="command", required=True))
    return parser


def _torso_inputs(args):
    """Rig, calibration and torso capture of a reconstruction command, checked against each other."""
    from .formats import read_calibration, read_capture, read_rig

    rig = read_rig(args.rig)
    calibration = read_calibration(args.calibration)
    if calibration.rig != rig.serial:
        raise FormatError(args.calibration, f"rig is {calibration.rig!r}, but rig.json is {rig.serial!r}")
    capture = read_capture(args.capture, rig)
    if capture.kind != "torso":
        raise FormatError(capture.source, f"kind is {capture.kind!r}: reconstruction needs a 'torso' capture")
    return rig, calibration, capture


def _cmd_reconstruct_arm(args) -> int:
    from . import parallel
    from .formats import write_json
    from .reconstruction import reconstruct_arm
    from .surface import write_ply

    parallel.reuse_freed_images()  # this process is ours: full-size images are freed and allocated again
    rig, calibration, capture = _torso_inputs(args)
    surface, report = reconstruct_arm(capture, rig, calibration, args.arm, progress=lambda m: print(f"  {m}", flush=True))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, surface.points, surface.normals, surface.faces, surface.data,
              comments=[f"torsoscan arm {args.arm} surface, mm, frame: {calibration.frame}"])
    report_path = Path(args.report) if args.report else out.with_suffix(".json")
    write_json(report_path, report)
    print(f"arm {args.arm}: {report['points']} points ({report['patches']} patches), "
          f"median precision {report['sigma_mm_median']:.3f} mm, {report['seconds']['total']:.1f} s")
    for cam_id, why in report["unusable_images"].items():
        print(f"image {cam_id} unusable: {why}", file=sys.stderr)
    print(f"wrote {out} and {report_path}")
    return 0


def _cmd_reconstruct(args) -> int:
    from . import parallel
    from .reconstruction import TorsoConfig, reconstruct_torso
    from .results import write_torso

    if args.arm_workers < 0:
        raise ValueError(f"--arm-workers is {args.arm_workers}: give 0 (one per core) or more")
    parallel.return_freed_images()  # this process is ours: each arm's images leave memory when it is done
    rig, calibration, capture = _torso_inputs(args)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise FileExistsError(f"{out}: already exists and is not empty (use --force to replace its files)")
    cfg = TorsoConfig(arm_workers=args.arm_workers)
    result = reconstruct_torso(capture, rig, calibration, cfg, progress=lambda m: print(f"  {m}", flush=True))
    write_torso(out, result)
    rep = result["report"]
    print(f"torso: {rep['points']} points, mesh {rep['mesh']['faces']} faces, {rep['seconds']['total']:.1f} s")
    for p in rep["registration"]["pairs"]:
        if p["average_normal_distance_mm"] is None:
            print(f"  {p['a']}-{p['b']}: no point-patch pairs (left out)")
            continue
        print(f"  {p['a']}-{p['b']}: average normal distance {p['average_normal_distance_mm']:.3f} mm, "
              f"{p['matched_fraction']:.0%} of {p['a']}'s points matched, {p['overlap_matched_fraction']:.1%} of the overlap")
    for warning in rep.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    for arm, why in rep["failed_arms"].items():
        print(f"arm {arm} not reconstructed: {why}", file=sys.stderr)
    print(f"wrote {out / 'torso.ply'}, {out / 'torso-mesh.ply'} and {out / 'report.json'}")
    if rep["status"] == "partial":
        print("torsoscan reconstruct: PARTIAL torso: " + "; ".join(rep["problems"]), file=sys.stderr)
    if rep["status"] == "failed":
        # the files stay for inspection, but the torso is not presented as good
        print("torsoscan reconstruct: REGISTRATION FAILED, do not use this torso:\n  " + "\n  ".join(rep["problems"]),
              file=sys.stderr)
        return 3
    return 0


def run(args) -> int:
    """Run a parsed command: its exit status, 2 with the message on standard error for bad input."""
    try:
        return args.func(args)
    except (FormatError, FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"torsoscan {args.command}: {exc}", file=sys.stderr)
        return 2


def main(argv=None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
