"""Small valid boundary files to break in the bad-input tests."""

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

RIG = {
    "format": "torso-rig/1",
    "serial": "RIG-T",
    "arms": [{"id": "A", "cameras": ["A1", "A2"], "projector": "PA"},
             {"id": "B", "cameras": ["B1"], "projector": "PB"}],
    "cameras": {c: {"width": 40, "height": 30, "pixel_size_mm": 0.01, "nominal_focal_mm": 8.0, "model": "t"}
                for c in ("A1", "A2", "B1")},
}


def write(path: Path, obj) -> Path:
    path.write_text(json.dumps(obj))
    return path


def image(value=100, shape=(30, 40), dtype=np.uint8):
    img = np.full(shape, value, dtype=dtype)
    img[5:10, 5:10] = 0
    return img


def bundle(folder: Path, cameras=("A1", "A2", "B1"), kind="torso", images=None, **extra) -> Path:
    """A capture bundle folder; ``images`` overrides camera -> array or bytes."""
    (folder / "images").mkdir(parents=True)
    entries = []
    for cam in cameras:
        data = (images or {}).get(cam, image())
        if isinstance(data, np.ndarray):
            data = cv2.imencode(".png", data)[1].tobytes()
        (folder / "images" / f"{cam}.png").write_bytes(data)
        entries.append({"camera": cam, "file": f"images/{cam}.png", "sha256": hashlib.sha256(data).hexdigest()})
    manifest = {"format": "torso-capture/1", "kind": kind, "rig": "RIG-T",
                "captured_at": "2026-11-22T09:30:00+00:00", "images": entries}
    if kind == "testfield":
        manifest.update(testfield="tower", pose=0)
    manifest.update(extra)
    write(folder / "capture.json", manifest)
    return folder
