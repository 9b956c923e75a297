"""The ``torsoscan`` command line: the engine's commands and the analysis' (``compare``, ``indices``).

The engine's commands live in :mod:`recon_engine.cli`, which never imports
``analysis``; this module adds the analysis commands to them, so imports run
one way. The installed ``torsoscan`` and ``python -m analysis.cli`` run this.

Exit status 0 on success; non-zero with a message on standard error that
names the file and the problem otherwise (capture-format spec, section 6).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from recon_engine import cli as engine_cli


def _point_arg(text: str, name: str):
    try:
        v = [float(t) for t in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        raise ValueError(f"--{name} {text!r}: expected X,Y,Z in mm (the torso's frame)")
    return v


def _f(v, spec: str = ".2f") -> str:
    """A number for the terminal; "n/a" for an unknown (None, NaN) value."""
    try:
        return "n/a" if v is None or v != v else format(v, spec)
    except (TypeError, ValueError):
        return "n/a"


def _cmd_compare(args) -> int:
    from .compare import compare_torsos, write_comparison
    from .torso import read_torso

    mdc = None
    if args.mdc:
        try:
            mdc = json.loads(Path(args.mdc).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise FileNotFoundError(f"{args.mdc}: no such file") from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise ValueError(f"{args.mdc}: not a JSON file of minimal detectable changes ({exc})") from None
    earlier, later = read_torso(args.earlier), read_torso(args.later)
    result = compare_torsos(earlier, later, mdc=mdc)
    paths = write_comparison(args.out, result)
    rep = result["report"]
    print(f"later torso registered to the earlier one: {rep['transform']['rotation_deg']:.2f} deg, "
          f"t = {', '.join(f'{v:.1f}' for v in rep['transform']['t'])} mm")
    sd = rep["signed_distance_mm"]
    print(f"average normal distance {_f(rep['average_normal_distance_mm'], '.3f')} mm, "
          f"{_f(rep['matched_fraction'], '.1%')} matched; signed distance mean {_f(sd['mean'])} mm "
          f"(p05 {_f(sd['p05'])}, p95 {_f(sd['p95'])})")
    for name, r in rep.get("regions", {}).items():
        if r["points"]:
            print(f"  {name}: mean {_f(r['mean'], '+.2f')} mm, p05 {_f(r['p05'], '+.2f')}, p95 {_f(r['p95'], '+.2f')} "
                  f"({r['points']} points)")
    if "growth" in rep:
        ch = rep["growth"]["change"]
        print(f"growth: trunk length {_f(ch['trunk_length_mm'], '+.1f')} mm, width {_f(ch['width_median_mm'], '+.1f')} mm")
    for w in rep.get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {paths['report']} and {paths['deformation']}")
    return 0


def _cmd_indices(args) -> int:
    from recon_engine.formats import write_json

    from .config import AnalysisConfig
    from .indices import compute_indices
    from .jsonsafe import clean
    from .torso import read_torso

    overrides = {}
    if args.vp:
        overrides["vertebra_prominens"] = _point_arg(args.vp, "vp")
    if args.sp:
        overrides["sacral_point"] = _point_arg(args.sp, "sp")
    cfg = AnalysisConfig()
    if args.facing:
        cfg = replace(cfg, indices=replace(cfg.indices, facing=args.facing))
    torso = read_torso(args.torso)
    try:
        rep = compute_indices(torso, cfg, overrides)
    except ValueError as exc:
        raise ValueError(f"{args.torso}: {exc}") from None
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, clean(rep))
    ld, sr = rep["lateral_deviation_mm"], rep["surface_rotation_deg"]
    print(f"lateral deviation RMS {_f(ld['rms'], '.1f')} mm, max {_f(ld['max'], '+.1f')} mm; surface rotation RMS "
          f"{_f(sr['rms'], '.1f')} deg, max {_f(sr['max'], '+.1f')} deg; hump {_f(rep['hump_mm'], '+.1f')} mm; "
          f"trunk imbalance {_f(rep['trunk_imbalance_mm'], '+.1f')} mm; asymmetry {_f(rep['asymmetry_mm'])} mm")
    for k, v in rep["landmarks"].items():
        print(f"  {k}: {', '.join(_f(c, '.1f') for c in v['position_mm'])} mm ({v['method']})")
    print(f"wrote {out}")
    return 0


def add_commands(sub) -> None:
    """Add the analysis commands to ``sub`` (an ``argparse`` subparsers action); each sets ``func``."""
    p = sub.add_parser("compare", help="register a later torso to an earlier one rigidly; deformation map and report")
    p.add_argument("--out", required=True, help="folder for report.json and deformation.ply")
    p.add_argument("--mdc", help="JSON of minimal detectable changes (figure -> mm) to flag the changes against")
    p.add_argument("earlier", metavar="EARLIER.ply")
    p.add_argument("later", metavar="LATER.ply")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser("indices", help="clinical surface indices of one torso (torso-indices/1)")
    p.add_argument("--out", required=True, help="indices.json to write")
    p.add_argument("--vp", metavar="X,Y,Z", help="vertebra prominens, corrected by a clinician (mm, torso frame)")
    p.add_argument("--sp", metavar="X,Y,Z", help="sacral point, corrected by a clinician (mm, torso frame)")
    p.add_argument("--facing", choices=["+x", "-x", "+y", "-y"],
                   help="the rig axis the patient's back faces (default: detected from the shape)")
    p.add_argument("torso", metavar="TORSO.ply")
    p.set_defaults(func=_cmd_indices)


def build_parser() -> argparse.ArgumentParser:
    """Every command: the engine's, then the analysis'."""
    parser = argparse.ArgumentParser(prog="torsoscan", description=engine_cli.DESCRIPTION)
    sub = parser.add_subparsers(dest="command", required=True)
    engine_cli.add_commands(sub)
    add_commands(sub)
    return parser


def main(argv=None) -> int:
    return engine_cli.run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
