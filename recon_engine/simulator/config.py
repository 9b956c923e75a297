"""Parameters of a simulated scenario, with commented defaults and two presets.

Lengths in mm, angles in degrees unless a name says otherwise. The defaults
describe the paper's rig (Detchev, Habib and Chang): four arms of five
low-cost cameras and one pattern projector each around a standing adolescent.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace


@dataclass(frozen=True)
class CameraConfig:
    width: int = 3000  # px
    height: int = 2000  # px
    pixel_size_mm: float = 0.0047  # 4.7 um
    focal_mm: float = 35.0  # nominal; each camera's true value differs
    focal_spread: float = 0.015  # relative 1-sigma of true against nominal focal length
    principal_point_sigma_px: float = 15.0  # 1-sigma offset of the principal point (at 3000 px)
    k1_range: tuple = (-0.25, 0.10)  # uniform; normalized-coordinate Brown–Conrady terms
    k2_sigma: float = 0.25
    p_sigma: float = 3e-4  # decentring, each of p1 and p2
    # --- terms beyond the old lens (issue 29): drawn from their own random stream, so a seed's
    # rig, scene and noise stay the same whatever they are; set by ``engine_lens`` to zero
    k3_sigma: float = 1.5  # r^6 radial term: 1-sigma moves a paper corner (r = 0.24) by 0.5 px; the engine fixes k3
    aspect_sigma: float = 0.002  # fy / fx - 1, 1-sigma (0.2 %; 95 % within 0.4 %): the engine estimates fx, fy
    skew_sigma: float = 0.0  # px, 1-sigma of K[0, 1]: modern sensors' pixel grids are square to far below this
    p3_sigma: float = 0.0  # Brown's higher-order decentring (1 + p3 r^2); off: no evidence of it in cheap lenses
    prism_sigma: float = 2e-4  # thin prism s1, s3 (r^2): a sensor tilted ~0.2 mrad against the lens
    prism2_sigma: float = 0.0  # thin prism s2, s4 (r^4)
    f_number: float = 5.6  # aperture: sets the depth of field
    focus_mm: float = 2350.0  # focused distance (about the near torso surface)
    blur_sigma_px: float = 0.5  # lens aberrations and pixel crosstalk (at 3000 px)
    supersample: int = 2  # rays per pixel along each axis
    full_well_e: float = 10000.0  # electrons at 255 DN
    read_noise_e: float = 5.0
    black_level_dn: float = 2.0
    prnu: float = 0.01  # photo-response non-uniformity, relative 1-sigma, fixed per camera
    vignetting: bool = True  # natural cos^4 fall-off


@dataclass(frozen=True)
class ProjectorConfig:
    width: int = 1024  # projector px
    height: int = 768
    distance_mm: float = 1700.0  # from the rig centre
    height_offset_mm: float = 350.0  # above the torso centre, clear of the cameras' views
    coverage_mm: float = 1000.0  # width of the lit frame at distance_mm
    focus_mm: float = 1550.0
    blur_sigma_px: float = 0.35  # optics at best focus (projector px)
    defocus_px_per_mm: float = 0.0015  # defocus sigma per mm away from focus (px of a 1024-px projector; f/2 lens)
    black_level: float = 0.02  # an unlit projector pixel still emits this fraction (contrast 50:1)
    power: float = 1.0  # irradiance of a lit pixel at distance_mm, normal incidence


@dataclass(frozen=True)
class RigConfig:
    serial: str = "RIG-SIM-0001"
    arms: tuple = ("A", "B", "C", "D")
    cameras_per_arm: int = 5
    first_arm_azimuth_deg: float = 45.0  # arm A views the back-left quadrant
    camera_radius_mm: float = 2500.0  # from the rig centre
    camera_spacing_mm: float = 800.0  # along the arc between neighbours
    camera_height_sigma_mm: float = 40.0  # mounting scatter about the torso centre height
    aim_sigma_mm: float = 30.0  # where each camera points, about the torso centre
    roll_sigma_deg: float = 1.5
    arm_rotation_max_deg: float = 1.0  # swing of arms B, C, D about the vertical at each capture
    arm_translation_max_mm: float = 4.0
    arm_tilt_max_deg: float = 0.05


@dataclass(frozen=True)
class SubjectConfig:
    torso: str = "makehuman"  # or "parametric"
    stature_mm: float = 1550.0  # an adolescent (the family spans 1300-1800)
    # the body's build, applied to the rest body about its spine line (so the spine and the truth stay put):
    build_width: float = 1.0  # across (x) scale: 0.9 slim .. 1.2 heavy
    build_depth: float = 1.0  # front-back (y) scale: 0.85 slim .. 1.4 heavy
    belly_mm: float = 0.0  # forward bulge of the abdomen at the navel (a heavy body: 20-40)
    breasts_mm: float = 0.0  # forward bulge of each breast (an adolescent girl: 15-35)
    hips: float = 1.0  # across scale at the pelvis, blending to 1 at the waist (a girl: 1.05-1.12)
    arm_abduction_deg: float = 0.0  # arms turned about the shoulders: + raised away from the trunk, - hanging closer
    # the forearms crossed in front of the chest (the MakeHuman body; arm_abduction_deg must be 0): the cameras in
    # front see forearms, not the front of the trunk
    arms_crossed: bool = False
    neck_hair_mm: float = 0.0  # hair over the back of the neck down to C7 (bulk, mm; 0: none)
    # the lumbar dimples (skin over the posterior superior iliac spines): depth of each hollow (slim 3-5 mm,
    # heavy 0-1.5: fat fills them), half their distance apart, and their height above the sacral point
    dimples_mm: float = 3.0
    dimple_half_spacing_mm: float = 45.0
    dimple_height_mm: float = 30.0
    pelvic_obliquity_mm: float = 0.0  # the right dimple this much higher than the left: the pelvis tilted
    # sideways about the sacral point (a leg-length difference), blended into the lumbar spine
    curve: str = "S"  # "C" (one thoracolumbar curve) or "S" (right thoracic, left lumbar)
    thoracic_apex: float = 0.62  # apex level as a fraction sacrum (0) -> C7 (1): about T8
    lumbar_apex: float = 0.22  # about L2
    lateral_mm: float = 12.0  # lateral deviation of the spine at the main apex (towards the patient's right)
    rotation_deg: float = 10.0  # axial rotation at the main apex (raises the rib hump)
    secondary_ratio: float = 0.7  # the lumbar curve of an S, relative to the thoracic one
    hump_mm_per_deg: float = 0.3  # extra posterior rib prominence on the convex side
    albedo: float = 0.5  # skin, mean
    albedo_variation: float = 0.08  # relative amplitude of the slow variation
    subsurface_mm: float = 0.35  # light diffusing in skin blurs the projected pattern (1-sigma)
    sway_tilt_deg: float = 0.5  # posture sway between captures, max
    sway_yaw_deg: float = 1.5
    sway_shift_mm: float = 5.0
    breathing_mm: float = 3.0  # chest-wall excursion at the front, max; the back moves a third
    visit_yaw_deg: float = 5.0  # placement in the rig at a new visit, max
    visit_shift_mm: float = 20.0
    progression_deg: float = 5.0  # axial rotation added at the later visit
    growth: float = 0.012  # relative stature growth at the later visit


@dataclass(frozen=True)
class TestFieldConfig:
    name: str = "tower-sim"
    aruco_dictionary: str = "DICT_4X4_1000"
    sides: int = 8  # octagonal tower
    circumradius_mm: float = 450.0
    bottom_mm: float = 740.0  # lowest marker row's lower edge above the floor
    columns: int = 5  # markers per face, across
    rows: int = 10  # markers per face, up
    marker_mm: float = 40.0  # many small markers: more corners to pin down the principal point
    gap_mm: float = 20.0  # white margin between markers and around them
    sigma_mm: float = 0.05  # survey precision of one coordinate
    poses: int = 4
    pose_yaw_deg: float = 22.5  # turn between consecutive poses
    pose_shift_mm: float = 300.0  # max: large moves put targets at new depths along every camera's view
    pose_lift_mm: float = 150.0  # max
    pose_tilt_deg: float = 3.0  # max
    ambient: float = 0.55  # room light, relative to a lit projector pixel
    key_light: float = 0.45  # a soft light from above and behind the cameras


@dataclass(frozen=True)
class SceneConfig:
    wall_radius_mm: float = 3400.0  # dim room wall beyond the rig
    wall_albedo: float = 0.25
    floor_albedo: float = 0.2
    torso_ambient: float = 0.04  # room light left on during a torso capture


@dataclass(frozen=True)
class ConditionsConfig:
    """What real patients and rigs bring beyond the clean capture (issue 29 §2); the defaults add nothing.

    Each condition draws from its own random stream, so a seed's rig, body and
    noise stay the same whichever conditions are on.
    """

    # --- skin (torso captures only)
    specular: float = 0.0  # oily skin: share of the projectors' light reflected as a highlight (Blinn-Phong)
    shininess: float = 30.0  # exponent of the highlight lobe (oily skin 20-60)
    freckles_per_dm2: float = 0.0  # small brown spots, 1-3 mm across (a freckled child: 10-40)
    moles: int = 0  # darker spots 3-6 mm across, over the torso
    body_hair_per_cm2: float = 0.0  # dark strands 0.06 mm thick, 5-15 mm long (vellus hair is paler: 0)
    tattoo: bool = False  # one dark design of about 120 x 90 mm on the back
    underwear_top_mm: float | None = None  # top edge of a waistband above the sacral point (None: no underwear)
    # --- light and optics
    exposure_albedo: float = 0.0  # the skin albedo the rig's exposure is set for (0: for this patient's albedo)
    exposure_ev: tuple = ()  # (camera, EV): that camera's exposure off by EV stops (+: brighter)
    jpeg_quality: int = 0  # images stored as JPEG at this quality (0: PNG, lossless)
    # --- motion
    trigger_jitter_ms: float = 0.0  # 1-sigma of each camera's trigger time about the capture's
    sway_speed_mm_s: float = 5.0  # the upper body's speed in quiet standing (random horizontal direction)
    breathing_period_s: float = 4.0  # a child's breath at rest (15 per minute)


@dataclass(frozen=True)
class ScenarioConfig:
    """Everything that defines one simulated scenario; the seed makes it repeatable."""

    preset: str = "paper"
    seed: int = 0  # the installation: rig, lenses, test field, patient
    session: int = 0  # what differs between sessions: test-field poses, arm swings, posture, noise
    lens_changes: tuple = ()  # (camera, "pd" | "pp_x" | "pp_y" | "k1", amount): lenses disturbed since installation
    camera: CameraConfig = field(default_factory=CameraConfig)
    projector: ProjectorConfig = field(default_factory=ProjectorConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    subject: SubjectConfig = field(default_factory=SubjectConfig)
    testfield: TestFieldConfig = field(default_factory=TestFieldConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    conditions: ConditionsConfig = field(default_factory=ConditionsConfig)
    torso_cameras: tuple = ()  # cameras rendered in torso captures (the others are missing); empty: every camera
    # torso captures: (name, visit index); visit 0 is the baseline, visit 1 the
    # later visit with progression. Two captures of one visit differ in sway and breathing.
    captures: tuple = (("visit0-a", 0), ("visit0-b", 0), ("visit1-a", 1))

    def to_dict(self) -> dict:
        return asdict(self)


LENS_EXTRAS = ("k3_sigma", "aspect_sigma", "skew_sigma", "p3_sigma", "prism_sigma", "prism2_sigma")


def engine_lens(cfg: ScenarioConfig) -> ScenarioConfig:
    """``cfg`` with the lenses of the simulator before issue 29: exactly the engine's model with k3 = 0.

    The same seed then gives the same rig, scene and noise; only the lenses lack
    k3, the aspect ratio and the terms the engine cannot represent.
    """
    return replace(cfg, camera=replace(cfg.camera, **{k: 0.0 for k in LENS_EXTRAS}))


# reduced rigs: camera width x height (px) and the projector's (px), both about the paper's times width / 3000
REDUCED = {"tiny": (480, 320, (168, 126)),  # the tests: a whole scenario in seconds
           "demo": (720, 480, (252, 189)),  # make demo: denser torsos (about 3 mm between points) in minutes
           "cheap": (1000, 667, (350, 263))}  # a cheaper rig's cameras (issue 29 §2: coverage at 1000 x 667 px)
PRESETS = ("paper", *REDUCED)


def preset(name: str, **overrides) -> ScenarioConfig:
    """A named preset: ``"paper"`` (the paper's rig at full resolution), ``"tiny"`` or ``"demo"``.

    ``tiny`` keeps the geometry, the optics and the noise of ``paper`` but images
    of 480 x 320 px, with the pattern and blur scaled so that the projected
    pattern covers as many camera pixels as at paper scale: it renders a whole
    scenario in seconds, for tests.
    """
    if name == "paper":
        cfg = ScenarioConfig(preset="paper")
    elif name in REDUCED:
        width, height, projector = REDUCED[name]
        scale = width / 3000
        cam = CameraConfig(
            width=width, height=height, pixel_size_mm=0.0047 / scale,
            principal_point_sigma_px=15.0 * scale,
        )
        proj = ProjectorConfig(width=projector[0], height=projector[1])
        # markers large enough to be read at 2 mm per pixel
        tf = TestFieldConfig(poses=3, columns=3, rows=6, marker_mm=70.0, gap_mm=30.0)
        cfg = ScenarioConfig(preset=name, camera=cam, projector=proj, testfield=tf,
                             captures=(("visit0-a", 0),))
    else:
        raise ValueError(f"unknown preset {name!r}: choose {', '.join(['paper', *REDUCED])}")
    return replace(cfg, **overrides) if overrides else cfg
