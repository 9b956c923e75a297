"""Parameters of the analysis stages, with commented defaults.

Lengths in mm, angles in degrees unless a name says otherwise. One frozen
dataclass per stage, gathered in :class:`AnalysisConfig`; every public
function takes an optional config and falls back to these defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class SurfaceConfig:
    normal_neighbours: int = 12  # points in the local plane that gives a point's normal
    plane_neighbours: int = 6  # earlier-surface points whose mean plane a later point is measured against
    max_points: int = 250_000  # larger clouds are thinned (random, seeded) before any analysis
    seed: int = 0  # thinning and subsampling are repeatable


@dataclass(frozen=True)
class RigidConfig:
    """Robust rigid point-to-plane registration (no scale)."""

    initial_distance_mm: float = 40.0  # pairs farther apart are not used at the start (visit placement ~20 mm, 5 deg)
    min_distance_mm: float = 1.0  # the acceptance distance never tightens below this
    tighten_k: float = 3.0  # acceptance: k times the robust scale of the last iteration (outliers: changed regions)
    tukey_c: float = 4.685  # Tukey biweight constant, in robust standard deviations
    min_scale_mm: float = 0.05  # floor of the robust scale (about the noise of a reconstructed point)
    max_tangential: float = 3.0  # a pair whose point lies beyond this many point spacings off its plane's
    # footprint is over a hole or past the surface's edge: not a pair
    max_normal_angle_deg: float = 45.0  # point and plane normals further apart are not a pair
    max_iterations: int = 60
    tol_rotation_deg: float = 1e-4
    tol_translation_mm: float = 1e-3
    sample: int = 20_000  # moving points used in the adjustment (all are used for the final figures)
    cycle_max: int = 8  # stop when the pose comes back to one of up to this many iterations ago (0: never): the
    # pair set can flip between a few states for ever (one of the six mirror registrations of two synthetic backs
    # ran to max_iterations in a 4-cycle; stopping at the cycle moved no index by more than 1e-9)


@dataclass(frozen=True)
class CompareConfig:
    match_distance_mm: float = 3.0  # a later point this close (normal distance) to the earlier surface is matched
    map_distance_mm: float = 30.0  # beyond this, a point gets no deformation value (NaN): not the same skin
    region_bounds: tuple = (1 / 3, 2 / 3)  # upper/middle/lower back split, as fractions sacral point -> VP


@dataclass(frozen=True)
class IndicesConfig:
    facing: str | None = None  # posterior direction in the rig frame, e.g. "+y"; None: detected from the shape
    grid_mm: float = 2.0  # cell of the back's depth map (across and up)
    back_normal_deg: float = 80.0  # points whose outward normal is within this of the posterior direction: the back
    layer_mm: float = 10.0  # depth map: back points more than this in front of the cell's most posterior one are dropped
    gap_mm: float = 15.0  # a horizontal gap this wide separates the trunk from a hanging arm
    neck_width_ratio: float = 0.5  # VP: the level where the trunk narrows below this fraction of the shoulders
    section_step: float = 0.025  # spacing of the horizontal sections, as a fraction of the VP-SP distance
    end_margin: float = 0.05  # sections this close to VP or SP (fraction) are left out: landmarks' own shapes
    symmetry_search_mm: float = 50.0  # the symmetry point is searched this far either side of the VP-SP line
    symmetry_window_mm: float = 40.0  # half width of the profile compared with its mirror image
    # the line of symmetry: a step of d mm between rows 4 mm apart costs this times d^2 (mm of mirror misfit). Chosen
    # on the rendered demo re-scans' tuning bodies and the true surfaces' tuning bodies (seed 100): 0.3 cuts the
    # lateral deviation's re-scan change from 5.97 to 2.27 mm RMS and reads the true one without bias (mean
    # +0.02 mm, 6 bodies; 0.1: +0.36 mm and a larger scatter; 1.0: -1.46 mm)
    symmetry_step_penalty: float = 0.3
    line_smooth_mm: float = 8.0  # Gaussian smoothing (sigma) of the line of symmetry along the height
    rotation_window_mm: float = 12.0  # half width over which the surface normal at the symmetry line is averaged
    smooth_mm: float = 6.0  # Gaussian smoothing (sigma) of the depth map before profiles are read
    spine_depth_mm: float = 45.0  # skin to vertebral body centre at the symmetry line (adolescent, thoracic):
    # the spine midline is the symmetry line moved by this depth times the sine of the section's rotation
    spine_rotation: str = "section"  # rotation the spine midline model uses: "section" (surface_rotation_deg, the
    # whole transverse section, little affected by a rib hump off the midline) or "midline" (midline_rotation_deg,
    # the skin's slope at the symmetry line, as Formetric)
    section_half_height_mm: float = 4.0  # a transverse section: the trunk's points within this of its height
    section_iterations: int = 30  # mirror registration of a section (2D, robust)
    # a section whose registered mirror image lies within 5 mm of its outline on less than this share of its points
    # gets no surface rotation (an arm touching the trunk, a flank the scan missed). Chosen on the rendered demo
    # re-scans' tuning bodies (bench_rescans.py, seed 100, 20 scans): median share 0.94, 5th percentile 0.72;
    # sections at 0.7 or more differ from their neighbours' rotation by 0.23 deg (median), at 0.6-0.7 by 1.0 deg,
    # below 0.6 by 1.9-4.4 deg
    section_min_agreement: float = 0.7
    # the surface rotation is withheld where the unread sections around a side's apex (the midline skin rotation's
    # largest) span at least this fraction of SP-VP (indices.unread_apex_levels). Chosen on the tuning bodies (seed
    # 100, true surfaces, arms as drawn): four +10 deg scans have such runs, 0.05-0.1 long (arms hanging against
    # the flanks); on three of them (thoracic apexes) the neighbours read the apex's side 2.9-4.5 deg under the
    # midline skin rotation's peak; and on seed 200's bodies with their forearms crossed (body 1's +10 deg scan:
    # 0.2, where the largest read value was the other side's curve)
    unread_apex_min_span: float = 0.125
    # Gaussian smoothing (sigma, mm along the height) of the sections' surface rotation and midline skin rotation
    # before their largest values are taken, as the line of symmetry is smoothed: one 8 mm section's rotation
    # moves by about 0.3 deg when its slab shifts by 1 mm (a landmark 1 mm higher), and the largest value took
    # the section that moved most. Chosen on tuning seed 100 (true surfaces, 10 pairs / rendered demo re-scans,
    # 10 pairs): the surface rotation max's MDC 0.58 / 1.35 deg unsmoothed, 0.41 / 1.11 at 8 mm, 0.33 / 0.94 at
    # 12, 0.29 / 0.91 at 16 (little more gained; a vertebra is about 20 mm); the midline skin rotation max's
    # rendered MDC 6.8 deg unsmoothed, 4.9 at 8, 4.1 at 12. 0: no smoothing
    rotation_smooth_mm: float = 12.0
    hump_range_mm: tuple = (20.0, 100.0)  # distances from the symmetry line where the hump is measured
    yaw_band: float = 0.12  # the patient's yaw: mirror plane of the trunk within this fraction (of SP-VP) of SP
    mirror_band: float = 0.0  # asymmetry: trunk between SP and VP, extended by this fraction either end
    regions: tuple = (("lumbar", 0.0, 0.4), ("thoracolumbar", 0.4, 0.6), ("thoracic", 0.6, 1.0))  # SP=0, VP=1


@dataclass(frozen=True)
class AnalysisConfig:
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    rigid: RigidConfig = field(default_factory=RigidConfig)
    compare: CompareConfig = field(default_factory=CompareConfig)
    indices: IndicesConfig = field(default_factory=IndicesConfig)
