"""The whole-visit benchmark runs at main (a script nothing else runs between paper-scale runs rots unseen):
one tiny visit with the arms one after the other; the figures belong to ``docs/benchmarks.md``."""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_visit  # noqa: E402


def test_it_times_a_tiny_visit_and_reads_its_processes_memory(torso_scenario, tmp_path):
    out = tmp_path / "visit.json"
    assert bench_visit.main(["--scenario", str(torso_scenario), "--calibration",
                             str(torso_scenario / "truth" / "calibration.json"), "--arm-workers", "1",
                             "--json", str(out)]) == 0
    run = json.loads(out.read_text())["runs"][0]
    assert run["status"] == "ok" and run["points"] > 1000
    assert set(run["arms"]) == {"A", "B", "C", "D"}
    # a Python process with numpy and the engine loaded holds well over 50 MB: the sampling saw the command
    assert run["peak_all_processes_mb"] > 50
    assert run["wall_s"] >= run["seconds"]["total"]
