"""The ``torsoscan`` command line: thin commands that call the engine's stages.

Exit status 0 on success; non-zero with a message on standard error that
names the file and the problem otherwise (capture-format spec, section 6).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from .formats import FormatError


def _cmd_simulate(args) -> int:
    from .simulator.config import preset
    from .simulator.scenario import simulate

    cfg = preset(args.preset, seed=args.seed)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torsoscan", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="render a complete simulated scenario with its ground truth")
    p.add_argument("--preset", choices=["tiny", "paper"], default="tiny",
                   help="tiny: 480x320 px images for tests; paper: the paper's 3000x2000 px rig")
    p.add_argument("--out", required=True, help="scenario folder to write")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--torso", choices=["makehuman", "parametric"])
    p.add_argument("--curve", choices=["C", "S"], help="scoliotic curve pattern")
    p.add_argument("--rotation", type=float, help="axial rotation at the main apex (deg)")
    p.add_argument("--lateral", type=float, help="lateral deviation at the main apex (mm)")
    p.add_argument("--progression", type=float, help="rotation added at the later visit (deg)")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=_cmd_simulate)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (FormatError, FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"torsoscan {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
