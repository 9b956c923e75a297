"""Reconstruction results on disk: the torso files of the spec and arm surfaces between jobs.

``write_torso`` writes what ``torsoscan reconstruct`` writes (``torso.ply``,
``torso-mesh.ply``, ``report.json``), so the service and the command produce
the same files. ``write_arm_surface`` / ``read_arm_surface`` carry one arm's
surface (points, normals, patches, per-point data, viewing direction)
exactly, e.g. from a parallel arm job to the registration job.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .formats import write_json
from .surface import PointSurface, write_ply

TORSO_FILES = ("torso.ply", "torso-mesh.ply", "report.json")


def write_torso(out_dir, result: dict) -> list[Path]:
    """Write a torso (``reconstruct_torso`` / ``register_arms`` result) into ``out_dir``; the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frame = result["report"]["frame"]
    comments = [f"torsoscan torso, mm, frame: {frame}"]
    patient = result["report"].get("patient")
    if patient:
        # the torso file carries its own evidence of left and right, so `torsoscan indices TORSO.ply` has it
        comments.append(posterior_comment(patient["posterior"], patient.get("back_towards", ())))
    write_ply(out / "torso.ply", result["points"], result["normals"], None,
              {"sigma_mm": result["sigma_mm"].astype(np.float32), "fused": result["count"].astype(np.int32)},
              comments=comments)
    V, F = result["mesh"]
    write_ply(out / "torso-mesh.ply", V, None, F, comments=[f"torsoscan display mesh (Poisson), mm, frame: {frame}"])
    write_json(out / "report.json", result["report"])
    return [out / name for name in TORSO_FILES]


POSTERIOR_COMMENT = "torsoscan posterior"


def posterior_comment(posterior, back_towards=()) -> str:
    """The PLY comment that records where the patient's back faces (unit vector, the file's frame)."""
    x, y, z = (float(v) for v in posterior)
    arms = ",".join(back_towards) or "-"
    return f"{POSTERIOR_COMMENT} {x:.6f} {y:.6f} {z:.6f} back_towards {arms}"


def parse_posterior_comment(comments) -> dict | None:
    """``{"posterior": [x, y, z], "back_towards": [...], "source": "rig"}`` from a PLY's comments, or None."""
    for c in comments:
        if c.startswith(POSTERIOR_COMMENT + " "):
            parts = c.split()
            try:
                v = np.array([float(t) for t in parts[2:5]])
            except ValueError:
                return None
            if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v[:2]) < 1e-6:
                return None
            arms = parts[6].split(",") if len(parts) > 6 and parts[5] == "back_towards" and parts[6] != "-" else []
            return {"posterior": (v / np.linalg.norm(v)).tolist(), "back_towards": arms, "source": "rig"}
    return None


def arm_surface_bytes(surface: PointSurface) -> bytes:
    """One arm's surface as a compressed ``.npz`` (lossless)."""
    arrays = {"points": surface.points, "normals": surface.normals, "faces": surface.faces}
    if surface.view_direction is not None:
        arrays["view_direction"] = np.asarray(surface.view_direction)
    for name, values in surface.data.items():
        arrays[f"data.{name}"] = np.asarray(values)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def read_arm_surface(fileobj) -> PointSurface:
    """The surface written by :func:`arm_surface_bytes` (a path or a binary file object)."""
    with np.load(fileobj, allow_pickle=False) as z:
        data = {k[5:]: z[k] for k in z.files if k.startswith("data.")}
        view = z["view_direction"] if "view_direction" in z.files else None
        return PointSurface(z["points"], z["normals"], z["faces"], data, view)
