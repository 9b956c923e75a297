"""Reconstruction of one arm: from its images and calibration to a point surface.

Stages (each its own module): epipolar resampling of neighbouring images
(``epipolar``), region of interest and Harris features (``features``), NCC
matching along the epipolar rows with least-squares refinement
(``matching``), tracking through the arm's images (``tracking``),
multi-ray intersection (``multiview``) and the TIN surface (``surface``).
"""

from __future__ import annotations

import queue
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .epipolar import rig_centre, subject_depth_bounds
from .features import local_contrast
from .formats import Calibration, Capture, FormatError, Rig, load_image
from .kernels import warm_up
from .multiview import IntersectionConfig, intersect
from .parallel import cores
from .registration import (ICPatchConfig, Transform, chain_initial, multi_surface_registration, pair_fit,
                           patch_indices, weak_arms)
from .surface import (PointSurface, flank_faces, in_patches, local_quadrics, make_surface, nearest_points,
                      off_surface, off_surface_again, small_components, subset, window_curvature_bias,
                      window_obliquity_bias)
from .matching import reason_counts
from .tracking import TrackingConfig, track_images, track_windows

ROI_KEY = "roi_polygons"  # capture.json: {"A1": [[x, y], ...]} user-drawn regions (px)


@dataclass(frozen=True)
class ReconstructionConfig:
    subject_radius_mm: float = 400.0  # the subject lies within this of the rig centre (sets the disparity range)
    max_sigma_mm: float = 1.0  # points less precise than this (1-sigma, largest axis) are dropped
    # and points less precise than this many times the arm's median. Paper scale, arm B: median 0.049 mm, 40 points
    # beyond 10x; tiny preset (2.1 mm pixels): median 0.31-0.43 mm, none (max_sigma_mm decides there)
    max_sigma_factor: float = 10.0
    min_island_points: int = 10  # connected pieces of the surface with fewer points are dropped
    # the flanks' points (skin turned more than 80 deg from the arm's mean view, in no patch of its TIN) joined to
    # the skin by the end cameras' patches instead of dropped as islands: paper scale, coverage +1.1 to +2.5 points
    keep_flanks: bool = True
    min_contrast: float = 3.0  # grey levels: an image with less standard deviation is blank
    max_saturated: float = 0.2  # fraction of pixels at 255 above which an image is overexposed
    min_sharpness: float = 0.25  # high-frequency share of the pattern's contrast; below it, out of focus
    # an image still used, but with more of its pixels saturated than this, is named in the report's warnings:
    # paper scale, seed 35, arm A: 0.03-0.07 % saturated in a clean capture, 16.4 % with the middle camera 1 EV
    # over, which raised the arm's RMS 1.40 times (seed 34) while max_saturated let the image through
    warn_saturated: float = 0.02
    # every kept point refined on the weighted quadric through its nearest points (surface.local_quadrics): moved
    # onto it (onto_local_quadric), and out of the matching window's curvature bias (window_curvature_correction,
    # surface.window_curvature_bias: the window matches the skin's mean height over what it covers). Cheaper rig
    # (1000 x 667 px), seed 41 (tuning), arms A-D with the fill, our calibration, RMS to the true skin: 0.133-0.167
    # mm as intersected; 40 neighbours: 0.124-0.155 onto the quadric, 0.111-0.137 corrected, 0.098-0.122 both; both
    # with 24 neighbours 0.106-0.128, 60: 0.095-0.120, 100: 0.097-0.123 (40: nearly 60's, from fewer neighbours)
    local_quadric_neighbours: int = 40  # 0: no refinement
    onto_local_quadric: bool = True
    # mm, at most this Gaussian scale of the neighbours of the quadric the points move onto (the curvature's fit
    # takes the points' own spacing): on sparse points the 40 neighbours span more skin than a quadric describes.
    # Tiny preset (2 mm pixels, points 7 mm apart), arm A, true calibration: RMS 0.458 mm as intersected, 0.592 onto
    # the quadric of 40 neighbours
    onto_scale_mm: float = 8.0
    window_curvature_correction: bool = True
    # 1/mm (0: off): and out of the bias that grows with the skin's obliquity to the cameras
    # (surface.window_obliquity_bias: obliquity_bias g² (1/cos(theta) - 1) mm inside the skin, g mm of skin per
    # pixel). Measured, not derived. The cheaper rig's tuning seed 41 (g about 1.0 mm), arms A-D with the fill and
    # our calibration, after the corrections above: the points' signed distance to the true skin fitted
    # -0.016 - 0.020 (1/cos(theta) - 1) mm (per arm -0.014 to -0.040; without the fill -0.015); -0.01 mm where the
    # skin faces the cameras, -0.10 beyond 65 degrees. Paper scale (g 0.34 mm), seed 33, our calibration: -0.0032
    # (per arm -0.002 to -0.005), nearer g² (-0.0023) than g (-0.0068), and the g form, 0.02 px, raised seed 33's
    # torso RMS from 0.0237 to 0.0256 mm. The arms see their overlaps at different obliquities, so what is left of
    # the bias pulls the registration apart (docs/benchmarks.md, "The obliquity bias taken out")
    obliquity_bias: float = 0.02
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    intersection: IntersectionConfig = field(default_factory=IntersectionConfig)


def sharpness(image: np.ndarray, window: int = 15) -> float:
    """How much of the local contrast is fine detail: median |Laplacian| over local std where the pattern is.

    A focused projected pattern has sharp cell edges (about 0.5 and more);
    defocus removes the fine detail first.
    """
    img = np.asarray(image, dtype=np.float32)
    # the statistics on every third pixel of every third row: a ninth of the pixels tell the same medians
    c = local_contrast(img, window)[::3, ::3]
    lit = c > max(4.0, float(np.percentile(c, 95)) / 3)
    if lit.sum() < 100:
        return 0.0
    lap = cv2.Laplacian(img, cv2.CV_32F, ksize=1)
    lap = np.abs(lap, out=lap)[::3, ::3]  # in place: 24 MB per full-size float32 image at paper scale
    return float(np.median(lap[lit]) / np.median(c[lit]))


def saturated_share(image: np.ndarray) -> float:
    """The fraction of a grey image's pixels at full scale (8 or 16 bits; a float image in 8-bit levels)."""
    img = np.asarray(image)
    full = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(img.dtype, 254.5)
    return float(np.mean(img >= full))


def image_check(image: np.ndarray, cfg: ReconstructionConfig) -> tuple[str, str]:
    """``(problem, warning)``: why an image is unusable for matching ("" when usable), and what a usable
    image's operator should know ("" when nothing)."""
    img = np.asarray(image)
    scale = 255.0 / 65535.0 if img.dtype == np.uint16 else 1.0
    g = img.astype(np.float32)
    if scale != 1.0:
        g *= scale
    if g.std() < cfg.min_contrast:
        return f"blank (grey-value standard deviation {g.std():.1f} < {cfg.min_contrast})", ""
    sat = saturated_share(img)
    if sat > cfg.max_saturated:
        return f"overexposed ({sat:.0%} of pixels saturated)", ""
    s = sharpness(g)
    if s < cfg.min_sharpness:
        return f"out of focus (sharpness {s:.2f} < {cfg.min_sharpness})", ""
    if sat > cfg.warn_saturated:
        return "", (f"{sat:.0%} of its pixels saturated: the points it sees near its highlights are less "
                    f"precise; lower that camera's exposure and scan again")
    return "", ""


def arm_cameras(rig: Rig, arm_id: str) -> list[str]:
    for arm in rig.arms:
        if arm.id == arm_id:
            return list(arm.cameras)
    raise ValueError(f"rig {rig.serial} has no arm {arm_id!r} (arms: {', '.join(a.id for a in rig.arms)})")


def reconstruct_arm(capture: Capture, rig: Rig, calibration: Calibration, arm_id: str,
                    cfg: ReconstructionConfig | None = None, progress=lambda msg: None) -> tuple[PointSurface, dict]:
    """The point surface of what arm ``arm_id`` sees in a torso ``capture``.

    Points are in the calibration's frame (mm). Unusable or missing images
    are skipped and named in the report; at least two usable images are needed.
    Returns ``(surface, report)``.
    """
    cfg = cfg or ReconstructionConfig()
    t0 = time.perf_counter()
    ids = arm_cameras(rig, arm_id)
    unusable = {}
    images, cams, used = [], [], []
    polygons = (capture.extra or {}).get(ROI_KEY) or {}
    warnings = []  # appended by the loading threads (list.append is atomic); sorted below

    def usable(cam_id):
        """(grey image in 8-bit levels, "") or (None, why it is unusable). An 8-bit image stays uint8 (a quarter
        of float32's memory; tracking converts each image as it resamples it); a 16-bit one becomes float32."""
        if cam_id not in calibration.cameras:
            return None, "not in the calibration"
        if cam_id not in capture.cameras:
            return None, "missing from the capture"
        try:
            image = load_image(capture, cam_id, rig)
        except FormatError as exc:
            return None, f"unreadable: {exc}"
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        why, warning = image_check(image, cfg)
        if why:
            return None, why
        if warning:
            warnings.append(f"image {cam_id}: {warning}")
        if image.dtype == np.uint16:
            image = (image.astype(np.float32) * (255.0 / 65535.0))
        return image if image.dtype == np.uint8 else image.astype(np.float32), ""

    # decoding and checking the images on threads (OpenCV and numpy release the GIL); the order is kept. The
    # matching's compiled kernels load meanwhile
    with ThreadPoolExecutor(cores(cfg.tracking.matching.threads)) as pool:
        kernels = pool.submit(warm_up)
        loaded = list(pool.map(usable, ids))
        kernels.result()
    for cam_id, (image, why) in zip(ids, loaded):
        if why:
            unusable[cam_id] = why
            continue
        images.append(image)
        cams.append(calibration.cameras[cam_id])
        used.append(cam_id)
    warnings.sort()  # the threads' order is not the cameras'
    for cam_id, why in unusable.items():
        progress(f"arm {arm_id}: image {cam_id} unusable: {why}")
    for warning in warnings:
        progress(f"arm {arm_id}: {warning}")
    if len(used) < 2:
        raise ValueError(f"arm {arm_id}: fewer than two usable images ("
                         + "; ".join(f"{c}: {w}" for c, w in unusable.items()) + ")")
    polys = [polygons.get(c) for c in used] if polygons else None
    centre = rig_centre(list(calibration.cameras.values()))
    progress(f"arm {arm_id}: matching and tracking through {', '.join(used)}")
    t1 = time.perf_counter()
    tr = track_images(images, cams, lambda p: subject_depth_bounds(p, centre, cfg.subject_radius_mm),
                      cfg.tracking, polys)
    t2 = time.perf_counter()
    focus = cfg.tracking.matching.blurred_above_px
    for cam_id, blur in zip(used, tr["blur_px"]):
        if blur > focus:
            # matched with the out-of-focus settings, which recover much but not all of the precision
            warnings.append(f"image {cam_id}: blurred (estimate {blur:.2f} px; in focus below {focus:.2f}): its "
                            f"points are less precise; check that camera's focus and scan again")
            progress(f"arm {arm_id}: {warnings[-1]}")
    progress(f"arm {arm_id}: intersecting {len(tr['tracks'])} tracks")
    res = intersect(cams, tr["tracks"], cfg.intersection)
    t3 = time.perf_counter()
    surface, reason, sigma = surface_from_intersection(res, cams, cfg)
    keep = reason == ""
    # the window each kept point was matched with (its tracks' pairs: out-of-focus pairs match with larger ones)
    window = track_windows(tr["tracks"], tr["blur_px"], cfg.tracking.matching)[keep]
    surface, shift = refine_on_local_quadrics(surface, cams, cfg, window_px=window)
    t4 = time.perf_counter()
    dropped = reason_counts(reason[~keep])
    rays = res["rays"][keep]
    report = {
        "arm": arm_id, "cameras": used, "unusable_images": unusable, "warnings": warnings,
        "points": int(keep.sum()), "tracks": int(len(tr["tracks"])), "dropped": dropped,
        "blur_px": {c: round(float(b), 3) for c, b in zip(used, tr["blur_px"])},
        "rays_per_point": {str(k): int((rays == k).sum()) for k in range(2, len(used) + 1)},
        "removed_rays": int(np.isfinite(tr["tracks"][..., 0]).sum() - res["used"].sum()),
        "sigma_mm_median": float(np.median(sigma[keep])) if keep.any() else None,
        "patches": int(len(surface.faces)), "pairs": tr["pairs"],
        # how far the refinement moved the points along their normals (mm; + towards the cameras)
        "refinement_shift_mm": ({"median": float(np.median(shift)), "p95_abs": float(np.percentile(np.abs(shift), 95))}
                                if len(shift) else None),
        "seconds": {"load": t1 - t0, "match_track": t2 - t1, "intersect": t3 - t2, "surface": t4 - t3,
                    "total": t4 - t0},
    }
    return surface, report


def refine_on_local_quadrics(surface: PointSurface, cams: list, cfg: ReconstructionConfig,
                             window_px=None) -> tuple:
    """The surface's points moved along their normals onto their local quadric and out of the matching window's
    curvature bias (``cfg``'s ``onto_local_quadric``, ``window_curvature_correction``; see
    :func:`recon_engine.surface.local_quadrics` and :func:`recon_engine.surface.window_curvature_bias`).

    Neighbours weigh by their precision (1 / sigma_mm²). No point moves farther than three times its own sigma_mm,
    nor than three times the arm's median sigma_mm: a quadric that a gap, the surface's edge or a wrong match
    beside it bends cannot carry a point off its own measurement. (With the first bound alone, paper scale, seed
    33, true calibration, a few dozen imprecise two-ray points per arm moved 0.3-0.65 mm, and the arms' largest
    distance to the skin rose from 0.32-0.44 to 0.41-0.49 mm; with both 0.35-0.48 mm. Tuning seed 41 of the
    cheaper rig: RMS as with the first alone, arm C's largest distance 2.72 mm instead of 3.26.) The
    patches, normals and per-point data stay. Returns ``(surface, shift)``, ``shift`` (N,) in mm along the
    normals; ``surface`` is not modified.

    ``window_px`` (px, a number or one per point): the least-squares window each point was matched with
    (:func:`recon_engine.tracking.track_windows`: an out-of-focus pair's ``blurred_lsm_window``); by default the
    in-focus ``lsm_window`` for every point. The points that growing (``grow_window``, 11 px) matched carry a
    larger bias and are under-corrected (the tracks do not say which stage matched them).
    """
    n = len(surface.points)
    if cfg.local_quadric_neighbours <= 0 or n < 6 or not (cfg.onto_local_quadric or cfg.window_curvature_correction
                                                         or cfg.obliquity_bias):
        return surface, np.zeros(n)
    sigma = np.asarray(surface.data["sigma_mm"], dtype=float)
    w = 1.0 / np.maximum(sigma, 1e-3) ** 2
    k = cfg.local_quadric_neighbours
    near = nearest_points(surface.points, k)  # one search serves both fits
    h = float(np.median(near[0][:, -1]))
    q = local_quadrics(surface.points, surface.normals, w, k, h, neighbours=near)
    shift = np.zeros(n)
    if cfg.onto_local_quadric:
        onto = q if h <= cfg.onto_scale_mm else local_quadrics(surface.points, surface.normals, w, k,
                                                               cfg.onto_scale_mm, neighbours=near)
        shift += onto[:, 0]
    if cfg.window_curvature_correction:
        m = cfg.tracking.matching
        window = (m.lsm_window or m.window) if window_px is None else window_px
        shift -= window_curvature_bias(q, surface.points, cams, window)
    if cfg.obliquity_bias:
        shift -= window_obliquity_bias(surface.points, surface.normals, cams, cfg.obliquity_bias)
    limit = 3 * np.minimum(sigma, np.median(sigma))
    shift = np.clip(shift, -limit, limit)
    return replace(surface, points=surface.points + shift[:, None] * surface.normals), shift


def surface_from_intersection(res: dict, cams: list, cfg: ReconstructionConfig) -> tuple:
    """The arm's surface from intersected tracks, after the surface filters: imprecise points, points off the
    local surface, islands of wrong matches that agree with each other, and the points that leaned on them.

    ``res``: :func:`recon_engine.multiview.intersect`'s result for ``cams`` (world -> camera). Returns
    ``(surface, reason, sigma)``: the kept points as a :class:`Surface` (mm, world frame), why each track was
    dropped (``""``: kept) and each track's largest standard deviation (mm; inf where not intersected).
    ``res`` is not modified.
    """
    reason = res["reason"].copy()
    sigma = np.full(len(reason), np.inf)
    ok = reason == ""
    sigma[ok] = np.sqrt(np.maximum(np.linalg.eigvalsh(res["cov"][ok])[:, -1], 0))
    reason[(reason == "") & (sigma > cfg.max_sigma_mm)] = "imprecise"
    precise = reason == ""
    if precise.any():
        # far less precise than the arm's typical point: two rays meeting at a narrow angle, where a wrong match
        # moves the point along them unseen (paper scale: a 7.6 mm stray at sigma 0.74 mm, the arm's median 0.05)
        reason[precise & (sigma > cfg.max_sigma_factor * np.median(sigma[precise]))] = "imprecise"
    keep = reason == ""
    # wrong matches of two-ray points show only against their neighbours
    tested = np.nonzero(keep)[0]
    first = off_surface(res["X"][tested])
    reason[tested[first["off"]]] = "off the local surface"
    keep = reason == ""
    surface = make_surface(res["X"][keep], cams, data={"sigma_mm": sigma[keep].astype(np.float32),
                                                       "rays": res["rays"][keep].astype(np.int32)})
    # precision along the skin's normal: what a normal distance to another arm's patch inherits (a point seen
    # obliquely is weak along its rays, mostly across the normal, so this is often far below sigma_mm)
    cov_n = np.einsum("ni,nij,nj->n", surface.normals, res["cov"][keep], surface.normals)
    surface = replace(surface, data={**surface.data, "sigma_normal_mm": np.sqrt(np.maximum(cov_n, 0)).astype(np.float32)})
    # islands: wrong matches that agree with each other, cut off from the skin by the TIN's edge rules;
    # they share no patch with the rest, so dropping them leaves the other points' patches and normals as they are.
    # With keep_flanks, the flanks (where the skin turns away from the arm's mean view and its TIN has no patch)
    # are joined to the skin by patches from the end cameras' views, only for this test: the registration's
    # patches stay the arm's TIN. Without them a third of the skin seen 60-70 deg off its normal is dropped
    kept = np.nonzero(keep)[0]
    island = small_components(len(kept), surface.faces, cfg.min_island_points)
    if cfg.keep_flanks:
        small = island
        flanks = flank_faces(surface.points, surface.faces, cams)
        island = small_components(len(kept), np.concatenate([surface.faces, flanks]), cfg.min_island_points)
        # the patches of the TIN's own islands that the flanks joined to the skin are dropped: such steep skin
        # pulled the registration off (surface.in_patches leaves patchless points out of it); their points stay
        surface = replace(surface, faces=surface.faces[~small[surface.faces].any(axis=1)])
    reason[kept[island]] = "island off the surface"
    keep = reason == ""
    surface = subset(surface, ~island)
    # the points whose neighbours in that test have been dropped since (wrong matches that agreed with them) are
    # tested again against the skin left around them. Paper scale, visit1-a, arm B with our calibration: a
    # two-ray point 6.9 mm off the skin, 7 mm from its nearest kept neighbour, passed the first test
    gone = reason[tested] != ""
    again = np.nonzero(~gone & gone[first["neighbours"]].any(axis=1))[0]
    if len(again):
        at = np.searchsorted(np.nonzero(keep)[0], tested[again])  # their places in the surface
        off = off_surface_again(surface.points, at, first["limits"])
        reason[tested[again[off]]] = "off the local surface"
        drop = np.zeros(len(surface.points), bool)
        drop[at[off]] = True
        surface = subset(surface, ~drop)
        keep = reason == ""
    return surface, reason, sigma


@dataclass(frozen=True)
class TorsoConfig:
    arm: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    icpatch: ICPatchConfig = field(default_factory=ICPatchConfig)
    fuse_cell_fraction: float = 0.6  # fusion cell: this fraction of the median point spacing
    # octree depth of the display mesh: its cells are the torso's extent (x1.1) / 2**depth. Paper scale, seed 33:
    # depth 9 gives 2 mm cells in 4.2-5.6 s, depth 8 4 mm cells in 1.6 s; at 800 x 1000 px (about 1 mm per
    # pixel) the pictures of the two could not be told apart by eye (docs/benchmarks.md, the whole visit)
    poisson_depth: int = 8
    mesh_trim_spacings: float = 3.0  # mesh vertices farther than this many point spacings from the data are cut
    # ... but never closer than this many mesh cells: a vertex of a cell the data cross lies up to about a cell
    # from them, and a closer cut strews pinholes over the skin (paper scale, depth 9, 1.28 mm: 15 % of the
    # vertices cut, most of them inside the measured skin)
    mesh_trim_cells: float = 1.0
    # arms reconstructed at once, each on its own thread of this process with its share of the cores (0: one per
    # core). Paper scale, seed 33, 2 cores (docs/benchmarks.md, the whole visit): two arms at once on one core each
    # take as long as two arm processes did (the four arms 36.9-38.9 s against 36.9-37.4 s) with less than half
    # the memory (the visit 0.86-0.94 GB against 2.15-2.17 GB; the command's allocator returns freed large
    # blocks); one arm at a time with both cores' threads takes 1.2-1.3 times as long
    arm_workers: int = 0


def fuse_points(points: np.ndarray, normals: np.ndarray, sigma: np.ndarray, cell_mm: float):
    """Points of overlapping surfaces fused: one precision-weighted mean per cell of ``cell_mm``.

    Returns ``(points, normals, sigma, count)``; ``count`` says how many
    measured points each fused point averages.
    """
    key = np.floor(points / cell_mm).astype(np.int64)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    w = 1.0 / np.maximum(sigma, 1e-6) ** 2
    W = np.bincount(inv, weights=w)
    P = np.column_stack([np.bincount(inv, weights=w * points[:, k]) for k in range(3)]) / W[:, None]
    Nn = np.column_stack([np.bincount(inv, weights=w * normals[:, k]) for k in range(3)])
    Nn /= np.maximum(np.linalg.norm(Nn, axis=1, keepdims=True), 1e-12)
    return P, Nn, 1.0 / np.sqrt(W), count


def poisson_cell_mm(points: np.ndarray, depth: int, scale: float = 1.1) -> float:
    """Edge (mm) of the finest octree cell of Open3D's Poisson reconstruction: the points' largest extent,
    enlarged by ``scale`` (Open3D's default 1.1), split ``2**depth`` times."""
    extent = float(np.max(np.ptp(np.asarray(points, dtype=float), axis=0))) if len(points) else 0.0
    return scale * extent / 2 ** depth


def poisson_mesh(points: np.ndarray, normals: np.ndarray, depth: int, trim_mm: float, trim_cells: float = 0.0):
    """A watertight display mesh (Open3D's screened Poisson), trimmed to the data. (vertices, faces).

    Vertices farther than ``max(trim_mm, trim_cells * cell)`` (mm) from every
    point are cut, with ``cell`` the octree's finest cell (:func:`poisson_cell_mm`):
    the mesh bridges gaps narrower than about twice that and leaves wider ones open.
    """
    from .o3d import o3d  # here, not at the top: a process that only reconstructs arms never needs it

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    V = np.asarray(mesh.vertices)
    from scipy.spatial import cKDTree

    far, _ = cKDTree(points).query(V, k=1)
    density = np.asarray(density)
    limit = max(trim_mm, trim_cells * poisson_cell_mm(points, depth))
    mesh.remove_vertices_by_mask((far > limit) | (density < np.quantile(density, 0.01)))
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def reconstruct_torso(capture: Capture, rig: Rig, calibration: Calibration, cfg: TorsoConfig | None = None,
                      progress=lambda msg: None) -> dict:
    """The whole torso: every arm reconstructed, registered by ICPatch and fused, in the reference arm's frame.

    Returns ``{"points", "normals", "sigma_mm", "mesh": (vertices, faces), "report"}``.
    """
    cfg = cfg or TorsoConfig()
    t0 = time.perf_counter()
    order = [a.id for a in rig.arms]
    reference = rig.reference_arm.id
    surfaces, arm_reports, failed = {}, {}, {}
    workers = min(len(order), cores(cfg.arm_workers))
    if workers > 1:
        outcomes = _arms_in_threads(capture, rig, calibration, order, cfg.arm, workers, progress)
    else:
        outcomes = ((arm, *_arm_outcome(capture, rig, calibration, arm, cfg.arm, progress)) for arm in order)
    for arm, result, error in outcomes:
        if error is None:
            surfaces[arm], arm_reports[arm] = result
            progress(f"arm {arm}: {arm_reports[arm]['points']} points in {arm_reports[arm]['seconds']['total']:.1f} s")
        else:
            failed[arm] = error
            progress(f"arm {arm} not reconstructed: {error}")
    if reference not in surfaces:
        raise ValueError(f"the reference arm {reference} could not be reconstructed: {failed.get(reference)}")
    arms_seconds = time.perf_counter() - t0
    return register_arms(surfaces, arm_reports, failed, rig, calibration, cfg, progress, arms_seconds=arms_seconds)


def _arm_outcome(capture, rig, calibration, arm, cfg, progress):
    """``(result, None)`` or ``(None, why)`` when the arm cannot be reconstructed."""
    try:
        return reconstruct_arm(capture, rig, calibration, arm, cfg, progress), None
    except ValueError as exc:
        return None, str(exc)


def _arms_in_threads(capture, rig, calibration, order, cfg, workers, progress):
    """Yield ``(arm, result, error)`` for every arm, reconstructed ``workers`` at a time on threads, in ``order``.

    The cores are shared out: each arm matches and intersects with ``cores() // workers`` threads (the compiled
    kernels, OpenCV and numpy's large operations release the GIL). The arms' progress messages reach
    ``progress`` on the calling thread.
    """
    threads = max(1, cores() // workers)
    cfg = replace(cfg, tracking=replace(cfg.tracking, matching=replace(cfg.tracking.matching, threads=threads)),
                  intersection=replace(cfg.intersection, threads=threads))
    messages = queue.Queue()
    progress(f"reconstructing arms {', '.join(order)}, {workers} at a time")
    with ThreadPoolExecutor(workers, thread_name_prefix="arm") as pool:
        futures = {arm: pool.submit(_arm_outcome, capture, rig, calibration, arm, cfg, messages.put) for arm in order}
        for arm in order:
            while True:
                try:
                    progress(messages.get(timeout=0.2))
                except queue.Empty:
                    if futures[arm].done():
                        break
            yield (arm, *futures[arm].result())
        while True:  # what the last arms said after the loop stopped listening
            try:
                progress(messages.get_nowait())
            except queue.Empty:
                break


def patient_posterior(rig: Rig, calibration: Calibration) -> dict | None:
    """Where the patient's back faces, from the rig's footplate (``rig.back_towards``) and the cameras.

    The horizontal unit vector (calibration frame, +Z up as the test field
    stands) from the centre of all cameras to the centre of the cameras of
    the arms the back faces; None when the rig does not say.
    """
    towards = getattr(rig, "back_towards", ())  # a rig-like object without a footplate says nothing
    if not towards:
        return None
    centres = {cid: np.asarray(c.C, float) for cid, c in calibration.cameras.items()}
    every = [centres[c] for c in rig.camera_ids if c in centres]
    back = [centres[c] for a in rig.arms if a.id in towards for c in a.cameras if c in centres]
    if not every or not back:
        return None
    v = np.mean(back, axis=0) - np.mean(every, axis=0)
    v[2] = 0.0
    if np.linalg.norm(v) < 1e-6:
        return None
    return {"posterior": (v / np.linalg.norm(v)).tolist(), "back_towards": list(towards),
            "source": "rig"}


def register_arms(surfaces: dict, arm_reports: dict, failed: dict, rig: Rig, calibration: Calibration,
                  cfg: TorsoConfig | None = None, progress=lambda msg: None, arms_seconds: float = 0.0) -> dict:
    """Arm surfaces (each in the calibration frame, mm) registered by ICPatch, fused and meshed.

    The second half of :func:`reconstruct_torso`, on its own so that the arms
    can be reconstructed elsewhere (e.g. in parallel jobs). ``surfaces`` maps
    arm id to :class:`PointSurface`, ``arm_reports`` to its report and
    ``failed`` to why an arm could not be reconstructed.
    """
    cfg = cfg or TorsoConfig()
    reference = rig.reference_arm.id
    if reference not in surfaces:
        raise ValueError(f"the reference arm {reference} could not be reconstructed: {failed.get(reference)}")
    order = [a.id for a in rig.arms if a.id in surfaces]
    t0 = time.perf_counter() - arms_seconds
    t1 = time.perf_counter()
    fused = surfaces  # every point goes into the torso; the registration sees the points in the arms' patches
    surfaces = {a: in_patches(s) for a, s in surfaces.items()}
    T, pairwise, closing = ({reference: Transform.identity()}, [], None)
    multi = {"transforms": T, "pairs": [], "sigmas": {}, "iterations": 0, "converged": True}
    problems, warnings, weak = [], [], {}

    def register(icfg):
        progress("pair-wise ICPatch around the rig")
        indices = patch_indices({a: surfaces[a] for a in order}, icfg)  # built once for both steps
        T, pairwise = chain_initial(surfaces, order, reference, icfg, progress=progress, indices=indices)
        unplaced = [a for a in order if a not in T]
        if unplaced:
            raise ValueError(f"arms {', '.join(unplaced)} overlap no placed neighbour under their "
                             "nominal placement")
        closing = None
        if len(order) > 2:
            # what the chain of pair-wise results leaves at the pair that closes the circle
            last = order[order.index(reference) - 1]
            closing = {"a": last, "b": reference,
                       **pair_fit(surfaces[last], surfaces[reference], T[last], T[reference], 2.0, icfg)}
        progress("multiple surface registration")
        multi = multi_surface_registration(surfaces, order, reference, T, icfg, progress=progress, indices=indices)
        return multi, pairwise, closing

    if len(order) > 1:
        try:
            multi, pairwise, closing = register(cfg.icpatch)
            weak = weak_arms(multi["strength"], surfaces, cfg.icpatch)
            if weak and cfg.icpatch.max_patch_edge is not None:
                # the compact patches may have thinned an overlap that held these arms: all patches instead
                progress(f"arms {', '.join(weak)} weakly held; registering again with all patches")
                try:
                    retry = register(replace(cfg.icpatch, max_patch_edge=None))
                    weak_retry = weak_arms(retry[0]["strength"], surfaces, cfg.icpatch)
                except (ValueError, np.linalg.LinAlgError) as exc:
                    progress(f"registration with all patches failed: {exc}")
                    retry, weak_retry = None, weak

                def worst(m, w):
                    return max((m["strength"][a]["position_sigma_mm"] for a in w), default=0.0)

                if retry and (len(weak_retry) < len(weak) or (len(weak_retry) == len(weak)
                                                              and worst(retry[0], weak_retry) < worst(multi, weak))):
                    warnings.append(f"with compact patches only, arms {', '.join(weak)} were weakly held: "
                                    "registered with all patches")
                    (multi, pairwise, closing), weak = retry, weak_retry
            T = multi["transforms"]
        except (ValueError, np.linalg.LinAlgError) as exc:
            # the arms stay where the calibration put them; the torso is marked as failed below
            problems.append(f"registration failed: {exc}")
            T = {a: T.get(a, Transform.identity()) for a in order}
    t2 = time.perf_counter()
    if not multi["converged"]:
        problems.append(f"the multiple registration did not converge in {multi['iterations']} iterations")
    # geometric strength: an arm the overlaps leave free to slide fits its neighbours however far it slid
    problems.extend(weak.values())
    for p in multi["pairs"]:
        if p["adjustment_pairs"] < cfg.icpatch.min_pairs:
            warnings.append(f"arms {p['a']} and {p['b']} barely overlap: {p['adjustment_pairs']} point-patch pairs "
                            f"(at least {cfg.icpatch.min_pairs} needed); the pair was left out of the adjustment")
        else:
            # what the two surfaces' own precision allows, and never more than the configured floor
            own = 3.0 * max(float(np.median(surfaces[p["a"]].data["sigma_mm"])),
                            float(np.median(surfaces[p["b"]].data["sigma_mm"])))
            limit = max(cfg.icpatch.max_average_distance_mm, own)
            if p["average_normal_distance_mm"] is None:
                problems.append(f"arms {p['a']} and {p['b']} do not fit: no point-patch pair within "
                                f"{p['acceptance_distance_mm']:.2f} mm at the solution")
            elif p["average_normal_distance_mm"] > limit:
                problems.append(f"arms {p['a']} and {p['b']} do not fit: average normal distance "
                                f"{p['average_normal_distance_mm']:.2f} mm > {limit:.2f} mm")
    for problem in problems:
        progress(f"registration problem: {problem}")
    for warning in warnings:
        progress(f"registration warning: {warning}")
    order = [a for a in order if a in T]
    pts = np.concatenate([T[a].apply(fused[a].points) for a in order])
    nrm = np.concatenate([T[a].rotate(fused[a].normals) for a in order])
    sig = np.concatenate([fused[a].data["sigma_mm"] * T[a].scale for a in order])
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    P, N, S, count = fuse_points(pts, nrm, sig, cfg.fuse_cell_fraction * spacing)
    t3 = time.perf_counter()
    progress(f"Poisson mesh of {len(P)} fused points")
    mesh = poisson_mesh(P, N, cfg.poisson_depth, cfg.mesh_trim_spacings * spacing, cfg.mesh_trim_cells)
    t4 = time.perf_counter()
    report = {
        "format": "torso-reconstruction/1",
        "points": int(len(P)),
        "frame": f"arm {reference} as calibrated ({calibration.frame})",
        # failed: the registration is not trustworthy; partial: registered, but arms are missing
        "status": "failed" if problems else ("partial" if failed else "ok"),
        "problems": problems + [f"arm {a} not reconstructed: {why}" for a, why in failed.items()],
        "warnings": [f"arm {a}: {w}" for a in sorted(arm_reports) for w in arm_reports[a].get("warnings", [])]
                    + warnings,
        "registration": {
            "pairs": multi["pairs"],
            "pairwise": pairwise,
            "closing_pair_after_pairwise_only": closing,
            "transforms": {a: T[a].to_dict() for a in order},
            "sigmas": multi["sigmas"],
            "strength": multi.get("strength", {}),
            "iterations": multi["iterations"], "converged": multi["converged"],
        },
        "arms": arm_reports, "failed_arms": failed,
        # the patient's facing from the rig's footplate: the analysis's evidence of left and right
        "patient": patient_posterior(rig, calibration),
        "fused_from": int(len(pts)), "point_spacing_mm": spacing,
        "mesh": {"vertices": int(len(mesh[0])), "faces": int(len(mesh[1]))},
        "seconds": {"arms": t1 - t0, "registration": t2 - t1, "fusion": t3 - t2, "mesh": t4 - t3, "total": t4 - t0},
    }
    return {"points": P, "normals": N, "sigma_mm": S, "count": count, "mesh": mesh, "report": report,
            "surfaces": fused, "transforms": T}
