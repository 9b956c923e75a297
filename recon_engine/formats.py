"""The boundary files of ``shared/spec/capture-format.md``: the one dataset interface.

Readers validate everything and raise :class:`FormatError` naming the file
(for a zip: the zip and the member) and the key or value at fault; unknown
keys are ignored. Writers are atomic (temporary file, then rename), so a
failed write never leaves a half-written file behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import stat
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from .camera import Camera

__all__ = [
    "FormatError", "CameraSpec", "Arm", "Rig", "TestField", "CaptureImage", "Capture", "Calibration",
    "read_rig", "write_rig", "rig_to_dict", "read_testfield", "write_testfield", "read_capture",
    "missing_cameras", "read_image_bytes", "load_image", "load_images", "to_float_image", "write_capture",
    "zip_capture", "read_calibration", "write_calibration", "read_json", "write_json",
    "parse_capture_manifest", "check_zip_members", "decode_image", "rig_from_dict",
]

RIG_FORMAT = "torso-rig/1"
TESTFIELD_FORMAT = "torso-testfield/1"
CAPTURE_FORMAT = "torso-capture/1"
CALIBRATION_FORMAT = "torso-calibration/1"
CAPTURE_KINDS = ("torso", "testfield")
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class FormatError(ValueError):
    """A boundary file breaks the spec; the message names the file and what is wrong."""

    def __init__(self, path, message: str):
        self.path = str(path)
        self.message = message
        super().__init__(f"{path}: {message}")


# --- JSON helpers ------------------------------------------------------------

def _default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json(path, obj) -> None:
    """Write ``obj`` as UTF-8 JSON (numpy values allowed), atomically."""
    text = json.dumps(obj, indent=2, default=_default, ensure_ascii=False) + "\n"
    _atomic_write_bytes(Path(path), text.encode("utf-8"))


def _parse_json(data: bytes, where, expected_format: str | None = None) -> dict:
    try:
        obj = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise FormatError(where, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise FormatError(where, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    if not isinstance(obj, dict):
        raise FormatError(where, "the top level must be a JSON object")
    if expected_format is not None:
        if "format" not in obj:
            raise FormatError(where, f"missing required key 'format' (expected {expected_format!r})")
        if obj["format"] != expected_format:
            raise FormatError(where, f"format is {obj['format']!r}, expected {expected_format!r}")
    return obj


def read_json(path, expected_format: str | None = None) -> dict:
    """Read a JSON object; check its ``format`` when ``expected_format`` is given."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except IsADirectoryError:
        raise FormatError(path, "is a directory, expected a JSON file") from None
    return _parse_json(data, path, expected_format)


def _require(obj: dict, key: str, where, context: str = ""):
    if key not in obj:
        raise FormatError(where, f"missing required key {key!r}{context}")
    return obj[key]


def _number(value, where, what, positive=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise FormatError(where, f"{what} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise FormatError(where, f"{what} must be positive, got {value!r}")
    return float(value)


def _integer(value, where, what, positive=False) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise FormatError(where, f"{what} must be an integer, got {value!r}")
    if positive and value <= 0:
        raise FormatError(where, f"{what} must be positive, got {value!r}")
    return int(value)


def _string(value, where, what) -> str:
    if not isinstance(value, str) or not value:
        raise FormatError(where, f"{what} must be a non-empty string, got {value!r}")
    return value


# --- rig.json ---------------------------------------------------------------

@dataclass(frozen=True)
class CameraSpec:
    id: str
    width: int  # px
    height: int  # px
    pixel_size_mm: float
    nominal_focal_mm: float
    model: str = ""


@dataclass(frozen=True)
class Arm:
    id: str
    cameras: tuple
    projector: str


@dataclass(frozen=True)
class Rig:
    serial: str
    arms: tuple
    cameras: dict  # camera id -> CameraSpec
    # where the patient stands: the arms the patient's back faces (the rig's footplate), e.g. ("A", "B");
    # optional key ``"patient": {"back_towards": [...]}`` of rig.json (readers of the spec ignore it).
    # It is the evidence of the patient's left and right that no shape noise can flip.
    back_towards: tuple = ()

    @property
    def camera_ids(self) -> list:
        """Every camera, arm by arm, in order along each arm."""
        return [c for arm in self.arms for c in arm.cameras]

    @property
    def reference_arm(self) -> Arm:
        return self.arms[0]

    def arm_of(self, camera_id: str) -> Arm:
        for arm in self.arms:
            if camera_id in arm.cameras:
                return arm
        raise KeyError(f"camera {camera_id!r} is on no arm of rig {self.serial}")


def rig_to_dict(rig: Rig) -> dict:
    return {
        "format": RIG_FORMAT,
        "serial": rig.serial,
        "arms": [{"id": a.id, "cameras": list(a.cameras), "projector": a.projector} for a in rig.arms],
        "cameras": {c.id: {"width": c.width, "height": c.height, "pixel_size_mm": c.pixel_size_mm,
                           "nominal_focal_mm": c.nominal_focal_mm, "model": c.model}
                    for c in (rig.cameras[i] for i in rig.camera_ids)},
        **({"patient": {"back_towards": list(rig.back_towards)}} if rig.back_towards else {}),
    }


def rig_from_dict(obj: dict, where="rig.json") -> Rig:
    if obj.get("format") != RIG_FORMAT:
        if "format" not in obj:
            raise FormatError(where, f"missing required key 'format' (expected {RIG_FORMAT!r})")
        raise FormatError(where, f"format is {obj['format']!r}, expected {RIG_FORMAT!r}")
    serial = _string(_require(obj, "serial", where), where, "serial")
    arms_raw = _require(obj, "arms", where)
    cams_raw = _require(obj, "cameras", where)
    if not isinstance(arms_raw, list) or not arms_raw:
        raise FormatError(where, "arms must be a non-empty list")
    if not isinstance(cams_raw, dict):
        raise FormatError(where, "cameras must be an object keyed by camera id")
    arms, seen_arms, seen_cams = [], set(), {}
    for k, a in enumerate(arms_raw):
        ctx = f" in arms[{k}]"
        if not isinstance(a, dict):
            raise FormatError(where, f"arms[{k}] must be an object")
        arm_id = _string(_require(a, "id", where, ctx), where, f"arms[{k}].id")
        if arm_id in seen_arms:
            raise FormatError(where, f"duplicate arm {arm_id!r}")
        seen_arms.add(arm_id)
        cams = _require(a, "cameras", where, f" in arm {arm_id!r}")
        if not isinstance(cams, list) or not cams:
            raise FormatError(where, f"arm {arm_id!r}: cameras must be a non-empty list")
        for c in cams:
            _string(c, where, f"arm {arm_id!r} camera id")
            if c in seen_cams:
                raise FormatError(where, f"duplicate camera {c!r} (in arm {seen_cams[c]!r} and arm {arm_id!r})")
            seen_cams[c] = arm_id
            if c not in cams_raw:
                raise FormatError(where, f"arm {arm_id!r} lists camera {c!r}, which has no entry under 'cameras'")
        projector = _string(_require(a, "projector", where, f" in arm {arm_id!r}"), where, f"arm {arm_id!r} projector")
        arms.append(Arm(arm_id, tuple(cams), projector))
    specs = {}
    for cam_id, c in cams_raw.items():
        if cam_id not in seen_cams:
            raise FormatError(where, f"camera {cam_id!r} is on no arm")
        ctx = f" for camera {cam_id!r}"
        if not isinstance(c, dict):
            raise FormatError(where, f"camera {cam_id!r} must be an object")
        specs[cam_id] = CameraSpec(
            cam_id,
            _integer(_require(c, "width", where, ctx), where, f"camera {cam_id!r} width", positive=True),
            _integer(_require(c, "height", where, ctx), where, f"camera {cam_id!r} height", positive=True),
            _number(_require(c, "pixel_size_mm", where, ctx), where, f"camera {cam_id!r} pixel_size_mm", positive=True),
            _number(_require(c, "nominal_focal_mm", where, ctx), where, f"camera {cam_id!r} nominal_focal_mm", positive=True),
            str(c.get("model", "")),
        )
    return Rig(serial, tuple(arms), specs, _back_towards(obj, seen_arms, where))


def _back_towards(obj: dict, arms: set, where) -> tuple:
    """The optional ``patient.back_towards`` of rig.json: arm ids the patient's back faces."""
    patient = obj.get("patient")
    if patient is None:
        return ()
    if not isinstance(patient, dict):
        raise FormatError(where, "patient must be an object, e.g. {\"back_towards\": [\"A\", \"B\"]}")
    towards = patient.get("back_towards")
    if towards is None:
        return ()
    if not isinstance(towards, list) or not towards:
        raise FormatError(where, "patient.back_towards must be a non-empty list of arm ids")
    for a in towards:
        if not isinstance(a, str) or a not in arms:
            raise FormatError(where, f"patient.back_towards names {a!r}, which is no arm of the rig "
                                     f"(arms: {', '.join(sorted(arms))})")
    if len(set(towards)) != len(towards):
        raise FormatError(where, "patient.back_towards names an arm twice")
    return tuple(towards)


def read_rig(path) -> Rig:
    """Read and validate ``rig.json``."""
    return rig_from_dict(read_json(path), Path(path))


def write_rig(path, rig: Rig) -> None:
    write_json(path, rig_to_dict(rig))


# --- testfield.json ---------------------------------------------------------

@dataclass(frozen=True)
class TestField:
    __test__ = False  # not a pytest test class

    name: str
    aruco_dictionary: str
    markers: dict  # marker id (int) -> (4, 3) corners in mm, TL, TR, BR, BL
    sigma_mm: float

    def corners(self):
        """Marker ids (M,) sorted, and their corners (M, 4, 3) in mm."""
        ids = np.array(sorted(self.markers), dtype=int)
        return ids, np.array([self.markers[i] for i in ids]).reshape(-1, 4, 3)


def read_testfield(path) -> TestField:
    """Read and validate ``testfield.json``."""
    import cv2

    path = Path(path)
    obj = read_json(path, TESTFIELD_FORMAT)
    name = _string(_require(obj, "name", path), path, "name")
    dictionary = _string(_require(obj, "aruco_dictionary", path), path, "aruco_dictionary")
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise FormatError(path, f"aruco_dictionary {dictionary!r} is not an OpenCV predefined dictionary")
    markers_raw = _require(obj, "markers", path)
    if not isinstance(markers_raw, dict) or not markers_raw:
        raise FormatError(path, "markers must be a non-empty object keyed by marker id")
    markers = {}
    for key, corners in markers_raw.items():
        if not re.fullmatch(r"\d+", str(key)):
            raise FormatError(path, f"marker id {key!r} is not a non-negative integer")
        mid = int(key)
        if mid in markers:
            raise FormatError(path, f"duplicate marker id {key!r}")
        try:
            arr = np.array(corners, dtype=float)
        except (TypeError, ValueError):
            raise FormatError(path, f"marker {key}: corners must be four [x, y, z] triples") from None
        if arr.shape != (4, 3) or not np.all(np.isfinite(arr)):
            raise FormatError(path, f"marker {key}: corners must be four finite [x, y, z] triples, got shape {arr.shape}")
        markers[mid] = arr
    sigma = _number(_require(obj, "sigma_mm", path), path, "sigma_mm")
    if sigma < 0:
        raise FormatError(path, f"sigma_mm must not be negative, got {sigma}")
    return TestField(name, dictionary, markers, sigma)


def write_testfield(path, tf: TestField) -> None:
    write_json(path, {
        "format": TESTFIELD_FORMAT, "name": tf.name, "aruco_dictionary": tf.aruco_dictionary,
        "markers": {str(k): np.asarray(v, float).tolist() for k, v in sorted(tf.markers.items())},
        "sigma_mm": float(tf.sigma_mm),
    })


# --- capture bundle -----------------------------------------------------------

@dataclass(frozen=True)
class CaptureImage:
    camera: str
    file: str
    sha256: str


@dataclass(frozen=True)
class Capture:
    source: Path  # the bundle folder or .zip
    kind: str
    rig: str
    captured_at: str
    images: tuple
    testfield: str | None = None
    pose: int | None = None
    extra: dict = field(default_factory=dict)  # other keys of capture.json, kept (e.g. ROI polygons)
    prefix: str = ""  # inside a zip: the folder holding capture.json ("" at the root)

    @property
    def cameras(self) -> list:
        return [im.camera for im in self.images]

    def image(self, camera: str) -> CaptureImage:
        for im in self.images:
            if im.camera == camera:
                return im
        raise KeyError(f"{self.source}: no image of camera {camera!r}")

    def where(self, member: str):
        """How errors name a file of the bundle."""
        return f"{self.source}!{self.prefix}{member}" if self.is_zip else self.source / member

    @property
    def is_zip(self) -> bool:
        return self.source.is_file()


def _check_zip_members(zf: zipfile.ZipFile, path: Path) -> None:
    for info in zf.infolist():
        name = info.filename
        p = PurePosixPath(name)
        if name.startswith("/") or "\\" in name or re.match(r"^[A-Za-z]:", name) or ".." in p.parts:
            raise FormatError(path, f"zip member {name!r} lies outside the bundle")
        mode = (info.external_attr >> 16) & 0o170000
        if mode == stat.S_IFLNK:
            raise FormatError(path, f"zip member {name!r} is a symbolic link")


def _capture_manifest_location(zf: zipfile.ZipFile, path: Path) -> str:
    names = set(zf.namelist())
    if "capture.json" in names:
        return ""
    candidates = sorted(n for n in names if PurePosixPath(n).name == "capture.json" and len(PurePosixPath(n).parts) == 2)
    if len(candidates) == 1:
        return str(PurePosixPath(candidates[0]).parent) + "/"
    if not candidates:
        raise FormatError(path, "no capture.json at the zip's root (or inside one top-level folder)")
    raise FormatError(path, f"several capture.json in the zip: {', '.join(candidates)}")


def _parse_capture(obj: dict, where, source: Path, prefix: str, rig: Rig | None) -> Capture:
    if "format" not in obj:
        raise FormatError(where, f"missing required key 'format' (expected {CAPTURE_FORMAT!r})")
    if obj["format"] != CAPTURE_FORMAT:
        raise FormatError(where, f"format is {obj['format']!r}, expected {CAPTURE_FORMAT!r}")
    kind = _require(obj, "kind", where)
    if kind not in CAPTURE_KINDS:
        raise FormatError(where, f"kind is {kind!r}, expected one of {', '.join(CAPTURE_KINDS)}")
    rig_serial = _string(_require(obj, "rig", where), where, "rig")
    captured_at = _string(_require(obj, "captured_at", where), where, "captured_at")
    testfield = pose = None
    if kind == "testfield":
        testfield = _string(_require(obj, "testfield", where, " (a testfield capture names its test field)"),
                            where, "testfield")
        pose = _require(obj, "pose", where, " (a testfield capture gives its pose)")
        pose = _integer(pose, where, "pose")
        if pose < 0:
            raise FormatError(where, f"pose must not be negative, got {pose}")
    images_raw = _require(obj, "images", where)
    if not isinstance(images_raw, list):
        raise FormatError(where, "images must be a list")
    images, seen = [], {}
    for k, im in enumerate(images_raw):
        if not isinstance(im, dict):
            raise FormatError(where, f"images[{k}] must be an object")
        cam = _string(_require(im, "camera", where, f" in images[{k}]"), where, f"images[{k}].camera")
        file = _string(_require(im, "file", where, f" in images[{k}] (camera {cam!r})"), where, f"camera {cam!r} file")
        digest = _require(im, "sha256", where, f" in images[{k}] (camera {cam!r})")
        if not isinstance(digest, str) or not _HEX64.match(digest.lower()):
            raise FormatError(where, f"camera {cam!r}: sha256 must be 64 hex digits, got {digest!r}")
        if cam in seen:
            raise FormatError(where, f"duplicate camera {cam!r} (images[{seen[cam]}] and images[{k}])")
        seen[cam] = k
        if rig is not None and cam not in rig.cameras:
            raise FormatError(where, f"unknown camera {cam!r}: rig {rig.serial} has no such camera")
        p = PurePosixPath(file)
        if p.is_absolute() or ".." in p.parts or "\\" in file:
            raise FormatError(where, f"camera {cam!r}: file {file!r} lies outside the bundle")
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            raise FormatError(where, f"camera {cam!r}: file {file!r} is not PNG, TIFF or JPEG")
        images.append(CaptureImage(cam, file, digest.lower()))
    if rig is not None and rig_serial != rig.serial:
        raise FormatError(where, f"rig is {rig_serial!r}, but rig.json is {rig.serial!r}")
    known = {"format", "kind", "rig", "captured_at", "images", "testfield", "pose"}
    extra = {k: v for k, v in obj.items() if k not in known}
    return Capture(source, kind, rig_serial, captured_at, tuple(images), testfield, pose, extra, prefix)


def parse_capture_manifest(obj, where, rig: Rig | None = None) -> Capture:
    """A ``capture.json`` already loaded as JSON (e.g. received over HTTP), validated.

    The images themselves are not looked at. Errors name ``where``.
    """
    if not isinstance(obj, dict):
        raise FormatError(where, "capture.json must be a JSON object")
    return _parse_capture(obj, where, Path(str(where)), "", rig)


def check_zip_members(zf: zipfile.ZipFile, path) -> None:
    """Refuse a zip with a member outside the bundle (absolute, ``..``, drive letter) or a link."""
    _check_zip_members(zf, Path(path))


def read_capture(path, rig: Rig | None = None) -> Capture:
    """Read and validate a capture bundle (folder or .zip) without decoding its images.

    With ``rig``, cameras unknown to the rig and a different rig serial are
    errors. Missing image files (folder) or members (zip) are errors too.
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "capture bundle not found")
    if path.is_dir():
        manifest = path / "capture.json"
        if not manifest.is_file():
            raise FormatError(path, "no capture.json in the bundle folder")
        cap = _parse_capture(read_json(manifest), manifest, path, "", rig)
        root = path.resolve()
        for im in cap.images:
            f = path / im.file
            if f.is_symlink() and root not in f.resolve().parents:
                raise FormatError(f, f"camera {im.camera!r}: the image is a link to outside the bundle")
            if not f.is_file():
                raise FormatError(f, f"camera {im.camera!r}: image file is missing")
        return cap
    if not zipfile.is_zipfile(path):
        raise FormatError(path, "neither a bundle folder nor a zip file")
    with zipfile.ZipFile(path) as zf:
        _check_zip_members(zf, path)
        prefix = _capture_manifest_location(zf, path)
        where = f"{path}!{prefix}capture.json"
        cap = _parse_capture(_parse_json(zf.read(prefix + "capture.json"), where), where, path, prefix, rig)
        names = set(zf.namelist())
        for im in cap.images:
            if prefix + im.file not in names:
                raise FormatError(f"{path}!{prefix}{im.file}", f"camera {im.camera!r}: image file is missing")
    return cap


def missing_cameras(capture: Capture, rig: Rig) -> list:
    """Cameras of the rig with no image in the capture, in rig order."""
    have = set(capture.cameras)
    return [c for c in rig.camera_ids if c not in have]


def read_image_bytes(capture: Capture, camera: str) -> bytes:
    im = capture.image(camera)
    if capture.is_zip:
        with zipfile.ZipFile(capture.source) as zf:
            return zf.read(capture.prefix + im.file)
    return (capture.source / im.file).read_bytes()


def _truncated(data: bytes, suffix: str) -> bool:
    if suffix == ".png":
        return not data.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82")
    if suffix in (".jpg", ".jpeg"):
        return not data.rstrip(b"\x00").endswith(b"\xff\xd9")
    return False


def load_image(capture: Capture, camera: str, rig: Rig | None = None, *, verify: bool = True) -> np.ndarray:
    """The grayscale image of ``camera`` (uint8 or uint16, (height, width)).

    Checks the sha256 of the file's bytes against the manifest, that the file
    decodes completely, its bit depth (8 or 16), and with ``rig`` its size.
    """
    import cv2

    im = capture.image(camera)
    where = capture.where(im.file)
    data = read_image_bytes(capture, camera)
    if verify:
        actual = hashlib.sha256(data).hexdigest()
        if actual != im.sha256:
            raise FormatError(where, f"camera {camera!r}: sha256 mismatch (manifest {im.sha256}, file {actual})")
    return decode_image(data, where, camera, PurePosixPath(im.file).suffix.lower(), rig)


def decode_image(data: bytes, where, camera: str, suffix: str, rig: Rig | None = None) -> np.ndarray:
    """An image file's bytes decoded to grayscale (uint8 or uint16, (height, width)), checked.

    The file must decode completely, be 8 or 16 bits and, with ``rig``, have
    the size ``rig.json`` gives for ``camera``; errors name ``where``.
    """
    import cv2

    if _truncated(data, suffix):
        raise FormatError(where, f"camera {camera!r}: image is truncated (no end marker)")
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.size == 0:
        raise FormatError(where, f"camera {camera!r}: cannot decode the image (unreadable or truncated)")
    if arr.dtype not in (np.uint8, np.uint16):
        raise FormatError(where, f"camera {camera!r}: unsupported bit depth ({arr.dtype}); 8 or 16 bits are supported")
    if arr.ndim == 3:
        if arr.shape[2] == 4:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2GRAY)
        elif arr.shape[2] == 3:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
        elif arr.shape[2] == 1:
            arr = arr[:, :, 0]
        else:
            raise FormatError(where, f"camera {camera!r}: unsupported number of channels ({arr.shape[2]})")
    if rig is not None:
        spec = rig.cameras.get(camera)
        if spec is None:
            raise FormatError(where, f"unknown camera {camera!r}: rig {rig.serial} has no such camera")
        if arr.shape != (spec.height, spec.width):
            raise FormatError(where, f"camera {camera!r}: image is {arr.shape[1]}x{arr.shape[0]} px, "
                                     f"rig.json says {spec.width}x{spec.height}")
    return arr


def load_images(capture: Capture, rig: Rig | None = None) -> dict:
    """Every image of the capture, camera id -> array (see :func:`load_image`)."""
    return {c: load_image(capture, c, rig) for c in capture.cameras}


def to_float_image(img: np.ndarray) -> np.ndarray:
    """float32 image in [0, 1] from uint8 or uint16."""
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    return img.astype(np.float32)


def write_capture(dest, *, kind: str, rig: str, captured_at: str, images: dict, testfield: str | None = None,
                  pose: int | None = None, extra: dict | None = None, ext: str = "png",
                  jpeg_quality: int = 95) -> Capture:
    """Write a capture bundle folder ``dest`` with ``images`` (camera -> array), atomically.

    ``ext`` is the images' format (png, tif, jpg); ``jpeg_quality`` (1-100) is
    used for jpg. Refuses to replace an existing non-empty ``dest``.
    """
    import cv2

    dest = Path(dest)
    if dest.exists() and any(dest.iterdir()):
        raise FileExistsError(f"{dest}: already exists and is not empty")
    if kind not in CAPTURE_KINDS:
        raise ValueError(f"kind must be one of {', '.join(CAPTURE_KINDS)}, got {kind!r}")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    try:
        (tmp / "images").mkdir()
        entries = []
        for cam, arr in images.items():
            params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if ext.lower() in ("jpg", "jpeg") else []
            ok, buf = cv2.imencode(f".{ext}", arr, params)
            if not ok:
                raise ValueError(f"camera {cam!r}: cannot encode the image as {ext}")
            data = buf.tobytes()
            rel = f"images/{cam}.{ext}"
            (tmp / rel).write_bytes(data)
            entries.append({"camera": cam, "file": rel, "sha256": hashlib.sha256(data).hexdigest()})
        manifest = {"format": CAPTURE_FORMAT, "kind": kind, "rig": rig, "captured_at": captured_at}
        if kind == "testfield":
            manifest["testfield"] = testfield
            manifest["pose"] = int(pose)
        manifest.update(extra or {})
        manifest["images"] = entries
        write_json(tmp / "capture.json", manifest)
        if dest.exists():
            dest.rmdir()
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return read_capture(dest)


def zip_capture(folder, zip_path) -> Path:
    """A .zip of a bundle folder's contents, ``capture.json`` at the root."""
    folder, zip_path = Path(folder), Path(zip_path)
    tmp = zip_path.with_name(f".{zip_path.name}.tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
        for f in sorted(folder.rglob("*")):
            if f.is_file():
                zf.write(f, f.relative_to(folder).as_posix())
    os.replace(tmp, zip_path)
    return zip_path


# --- calibration.json -------------------------------------------------------------

@dataclass(frozen=True)
class Calibration:
    rig: str
    calibrated_at: str
    frame: str
    cameras: dict  # camera id -> Camera
    extra: dict = field(default_factory=dict)  # any other top-level keys, written back


def read_calibration(path) -> Calibration:
    """Read and validate ``calibration.json``."""
    path = Path(path)
    obj = read_json(path, CALIBRATION_FORMAT)
    rig = _string(_require(obj, "rig", path), path, "rig")
    when = _string(_require(obj, "calibrated_at", path), path, "calibrated_at")
    frame = _string(_require(obj, "frame", path), path, "frame")
    cams_raw = _require(obj, "cameras", path)
    if not isinstance(cams_raw, dict) or not cams_raw:
        raise FormatError(path, "cameras must be a non-empty object keyed by camera id")
    cameras = {}
    for cam_id, c in cams_raw.items():
        ctx = f" for camera {cam_id!r}"
        if not isinstance(c, dict):
            raise FormatError(path, f"camera {cam_id!r} must be an object")
        vals = {}
        for key in ("width", "height"):
            vals[key] = _integer(_require(c, key, path, ctx), path, f"camera {cam_id!r} {key}", positive=True)
        for key in ("fx", "fy", "cx", "cy"):
            vals[key] = _number(_require(c, key, path, ctx), path, f"camera {cam_id!r} {key}",
                                positive=key in ("fx", "fy"))
        arrays = {}
        for key, shape in (("dist", (5,)), ("R", (3, 3)), ("C", (3,))):
            raw = _require(c, key, path, ctx)
            try:
                arr = np.array(raw, dtype=float)
            except (TypeError, ValueError):
                raise FormatError(path, f"camera {cam_id!r} {key}: not an array of numbers") from None
            if arr.shape != shape:
                raise FormatError(path, f"camera {cam_id!r} {key}: shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)):
                raise FormatError(path, f"camera {cam_id!r} {key}: holds a non-finite value")
            arrays[key] = arr
        R = arrays["R"]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
            raise FormatError(path, f"camera {cam_id!r} R: not a rotation matrix (orthonormal, determinant +1)")
        cameras[cam_id] = Camera(vals["width"], vals["height"], vals["fx"], vals["fy"], vals["cx"], vals["cy"],
                                 arrays["dist"], R, arrays["C"])
    extra = {k: v for k, v in obj.items() if k not in ("format", "rig", "calibrated_at", "frame", "cameras")}
    camera_extra = {cid: {k: v for k, v in c.items() if k not in ("width", "height", "fx", "fy", "cx", "cy", "dist", "R", "C")}
                    for cid, c in cams_raw.items()}
    if any(camera_extra.values()):
        extra["camera_extra"] = {k: v for k, v in camera_extra.items() if v}
    return Calibration(rig, when, frame, cameras, extra)


def write_calibration(path, calib: Calibration) -> None:
    extra = dict(calib.extra or {})
    camera_extra = extra.pop("camera_extra", {}) or {}
    cams = {}
    for cam_id, cam in calib.cameras.items():
        entry = cam.to_dict()
        for k, v in (camera_extra.get(cam_id) or {}).items():
            entry.setdefault(k, v)
        cams[cam_id] = entry
    obj = {"format": CALIBRATION_FORMAT, "rig": calib.rig, "calibrated_at": calib.calibrated_at,
           "frame": calib.frame, "cameras": cams}
    for k, v in extra.items():
        obj.setdefault(k, v)
    write_json(path, obj)
