"""What the API checks beyond the boundary formats, before the database sees anything.

The formats (``recon_engine.formats``) say what a file means; the database
has its own limits: column lengths, 32-bit integers, and PostgreSQL refuses
a NUL character in text and JSON. A value past one of them would be a 500
there (and silently stored by SQLite), so each is refused first, as a 400
naming the field and the value.
"""

import math
import re
from datetime import datetime
from typing import Annotated

from pydantic import Field, StringConstraints

# A rig's serial is a path segment of its page and of its files' names: letters, digits, dot, dash, underscore.
SERIAL_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
NO_NUL = r"^[^\x00]*$"
MAX_ID = 2**63 - 1  # the largest database id (a larger one overflows the query, not "not found")
MAX_POSES = 100  # test-field poses of one calibration
MAX_INTERVAL_DAYS = 3650
MAX_POSE = 10000  # a pose's number
MAX_CAMERA_PX = 100_000  # a side of a camera's image, px
MAX_JSON_DEPTH = 32
MAX_NOTES = 20_000  # notes are free text; Django's form limit (DATA_UPLOAD_MAX_MEMORY_SIZE) bounds the pages'


def text(max_length: int, min_length: int = 0, pattern: str = NO_NUL, strip: bool = False):
    """A string type of the Schemas: its limits show in the OpenAPI."""
    return Annotated[str, StringConstraints(max_length=max_length, min_length=min_length, pattern=pattern,
                                            strip_whitespace=strip)]


DbId = Annotated[int, Field(ge=1, le=MAX_ID)]


class Invalid(ValueError):
    """A field breaks a rule; the message names the field and the value."""


def _short(value, n=60) -> str:
    r = repr(value)
    return r if len(r) <= n else r[:n] + "…"


def check_json(obj, where: str) -> None:
    """No NUL character in any key or string, no non-finite number, and nested at most MAX_JSON_DEPTH deep."""
    stack = [(obj, where, 0)]
    while stack:
        value, path, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise Invalid(f"{path}: nested deeper than {MAX_JSON_DEPTH} levels")
        if isinstance(value, str):
            if "\x00" in value:
                raise Invalid(f"{path}: contains a NUL character ({_short(value)})")
        elif isinstance(value, float):
            if not math.isfinite(value):
                raise Invalid(f"{path}: {value} is not a finite number")
        elif isinstance(value, dict):
            for k, v in value.items():
                if "\x00" in k:
                    raise Invalid(f"{path}: key {_short(k)} contains a NUL character")
                stack.append((v, f"{path}.{k}", depth + 1))
        elif isinstance(value, list):
            stack.extend((v, f"{path}[{i}]", depth + 1) for i, v in enumerate(value))


def check_length(value: str, where: str, max_length: int) -> str:
    if len(value) > max_length:
        raise Invalid(f"{where}: longer than {max_length} characters ({len(value)}: {_short(value)})")
    return value


def check_param(value: str, where: str, max_length: int) -> str:
    """A path or query string: no NUL (PostgreSQL refuses it in a query), not longer than its column."""
    if "\x00" in value:
        raise Invalid(f"{where}: contains a NUL character ({_short(value)})")
    return check_length(value, where, max_length)


def check_serial(serial: str, where: str) -> str:
    if not re.match(SERIAL_PATTERN, serial):
        raise Invalid(f"{where}: serial {_short(serial)} is not allowed: use 1 to 64 letters, digits, '.', '-' "
                      "or '_', starting with a letter or digit")
    return serial


def check_capture(capture, manifest: dict, where: str) -> None:
    """A parsed capture.json within the columns it is stored in (CaptureSession, CaptureImage)."""
    check_json(manifest, where)
    check_length(capture.captured_at, f"{where}: captured_at", 64)
    try:
        datetime.fromisoformat(capture.captured_at)
    except ValueError:
        raise Invalid(f"{where}: captured_at {_short(capture.captured_at)} is not an ISO 8601 date and time") from None
    if capture.pose is not None and capture.pose > MAX_POSE:
        raise Invalid(f"{where}: pose {capture.pose} is too large (at most {MAX_POSE})")
    if capture.testfield is not None:
        check_length(capture.testfield, f"{where}: testfield", 200)
    for im in capture.images:
        check_length(im.camera, f"{where}: camera", 32)
        check_length(im.file, f"{where}: camera {im.camera!r} file", 200)


def check_rig(description: dict, engine_rig, where: str) -> None:
    """A rig.json within the columns of Rig and Camera, and with a serial that is safe in a URL and a path."""
    check_json(description, where)
    check_serial(engine_rig.serial, where)
    for arm in engine_rig.arms:
        check_length(arm.id, f"{where}: arm id", 32)
    for cam_id, spec in engine_rig.cameras.items():
        check_length(cam_id, f"{where}: camera id", 32)
        check_length(spec.model, f"{where}: camera {cam_id!r} model", 200)
        for side, px in (("width", spec.width), ("height", spec.height)):
            if px > MAX_CAMERA_PX:
                raise Invalid(f"{where}: camera {cam_id!r} {side} {px} px is too large (at most {MAX_CAMERA_PX})")
