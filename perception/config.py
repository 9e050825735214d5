"""Configuration: pydantic models, one per concern, read from YAML with ``yaml.safe_load``.

This is the one place where configuration is defined (``perception`` cannot import ``tridar_env``,
so the models of every concern live here and both packages use them). A mission YAML file has the
shape of :class:`MissionConfig`; every section is optional and falls back to documented physical
defaults. Unknown keys and bad values are rejected with a message naming the field, the value and
what was expected.

Example:
    >>> from perception.config import load_config
    >>> cfg = load_config("configs/missions/final_approach.yaml", sensor__tof__noise_sigma_m=0.03)
    >>> cfg.sensor.tof.noise_sigma_m
    0.03
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

__all__ = [
    "CONFIG_DIR",
    "BeamConfig",
    "ChaserConfig",
    "ConfigError",
    "CorridorConfig",
    "DockingEnvelopeConfig",
    "DynamicsConfig",
    "EnvConfig",
    "FaultsConfig",
    "FlashLidarConfig",
    "ICPConfig",
    "IntegrityConfig",
    "InitialStateConfig",
    "MaterialResponseConfig",
    "MissionConfig",
    "OccluderConfig",
    "OrbitConfig",
    "PAHConfig",
    "PipelineConfig",
    "PointingConfig",
    "RewardConfig",
    "ScanConfig",
    "ScanPlanConfig",
    "SensorConfig",
    "StrictModel",
    "TOFConfig",
    "TargetAttitudeConfig",
    "TargetConfig",
    "TriangulationConfig",
    "apply_overrides",
    "config_path",
    "flatten_overrides",
    "load_config",
    "load_yaml",
    "save_config",
    "shipped_configs",
]

#: Folder of the shipped YAML files (``configs/`` at the repository root).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
UnitFloat = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class ConfigError(ValueError):
    """A configuration file or override that does not validate; the message names every field."""


class StrictModel(BaseModel):
    """Base of every config model: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


# ---------------------------------------------------------------------------------------------
# Target
# ---------------------------------------------------------------------------------------------
class TargetConfig(StrictModel):
    """Which target to approach: a library name or a mesh file."""

    name: str = Field("cubesat", description="library name (cubesat, cygnss, iss_port, hubble) or mesh path")
    scale: PositiveFloat = 1.0
    port_position_m: Vec3 | None = None
    port_axis: Vec3 | None = None
    mass_kg: PositiveFloat | None = None
    reflectivity: UnitFloat = 0.5

    @model_validator(mode="after")
    def _port_pair(self) -> TargetConfig:
        if (self.port_position_m is None) != (self.port_axis is None):
            raise ValueError("port_position_m and port_axis must be given together")
        return self


# ---------------------------------------------------------------------------------------------
# Sensors
# ---------------------------------------------------------------------------------------------
class TriangulationConfig(StrictModel):
    """Triangulation subsystem: range noise sigma = k r^2, valid up to ``max_range_m``."""

    noise_k_per_m: NonNegFloat = Field(5e-4, description="sigma = k * r^2 [1/m]")
    min_range_m: NonNegFloat = 0.3
    max_range_m: PositiveFloat = 20.0
    min_signal: UnitFloat = Field(
        0.02, description="reflectivity * cos(incidence) below which the spot is too dim to locate"
    )

    @model_validator(mode="after")
    def _ranges(self) -> TriangulationConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m={self.min_range_m} must be below max_range_m={self.max_range_m}"
            )
        return self


class TOFConfig(StrictModel):
    """Pulsed time-of-flight LIDAR: constant noise + bias, link-budget maximum range.

    The received signal is ``reflectivity * cos(incidence) * power_fraction * (R_ref / r)^2``
    against a detection threshold of 1: ``max_range_ref_m`` is the range at which a white
    (reflectivity 1) surface at normal incidence at full power just reaches the threshold.
    Returns closer than ``saturation_range_m`` from surfaces brighter than
    ``saturation_reflectivity`` saturate the detector and are invalid.
    """

    noise_sigma_m: NonNegFloat = 0.025
    bias_m: FiniteFloat = 0.005
    max_range_ref_m: PositiveFloat = 3000.0
    power_fraction: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1.0
    saturation_range_m: NonNegFloat = 2.0
    saturation_reflectivity: UnitFloat = 0.3
    min_range_m: NonNegFloat = 0.5


class BeamConfig(StrictModel):
    """Laser footprint: full-angle divergence and the sub-rays that sample it."""

    divergence_rad: NonNegFloat = 5e-4
    subrays: Annotated[int, Field(ge=1, le=64)] = 5
    mixed_range_tolerance_m: PositiveFloat = Field(
        0.05, description="sub-ray ranges spread more than this -> mixed pixel (edge)"
    )


class PointingConfig(StrictModel):
    """Scanning-mirror pointing: angle quantisation and random jitter."""

    resolution_rad: NonNegFloat = 2e-5
    jitter_rad: NonNegFloat = 1e-5


class MaterialResponseConfig(StrictModel):
    """How surfaces return light: grazing dropout and the specular acceptance cone."""

    grazing_limit_deg: Annotated[float, Field(gt=0, le=90)] = 80.0
    specular_cone_deg: Annotated[float, Field(gt=0, le=90)] = 5.0


class OccluderConfig(StrictModel):
    """A sphere in the sensor frame that blocks rays (an arm, a boom, a visiting vehicle)."""

    center_m: Vec3
    radius_m: PositiveFloat


class FaultsConfig(StrictModel):
    """Fault and environment injection (all off by default)."""

    dropout_prob: UnitFloat = 0.0
    spurious_prob: UnitFloat = Field(0.0, description="per-sample probability of a stray-light return")
    blackout_start_frame: Annotated[int, Field(ge=0)] | None = None
    blackout_frames: Annotated[int, Field(ge=0)] = 0
    occluder: OccluderConfig | None = None


class ScanConfig(StrictModel):
    """Scan pattern selection and mirror limits."""

    pattern: Literal["lissajous", "rosette", "spiral", "raster"] = "rosette"
    n_points: Annotated[int, Field(ge=4, le=200_000)] = 1000
    sample_rate_hz: PositiveFloat = 10_000.0
    phase_step: FiniteFloat = Field(0.37, description="pattern phase advance per frame [rad]")
    max_mirror_accel_rad_s2: PositiveFloat = Field(
        200_000.0,
        description="optical-angle limit; ~1,000-point patterns over 30 deg in 0.1 s need ~1.5e5",
    )


class SensorConfig(StrictModel):
    """The TriDAR hybrid scanner (seed 000 section 4)."""

    fov_deg: tuple[PositiveFloat, PositiveFloat] = (30.0, 30.0)
    triangulation: TriangulationConfig = TriangulationConfig()
    tof: TOFConfig = TOFConfig()
    transition_range_m: PositiveFloat | None = Field(
        None, description="triangulation/TOF switch; default: where their noise models cross"
    )
    beam: BeamConfig = BeamConfig()
    pointing: PointingConfig = PointingConfig()
    material: MaterialResponseConfig = MaterialResponseConfig()
    faults: FaultsConfig = FaultsConfig()
    scan: ScanConfig = ScanConfig()

    @field_validator("fov_deg")
    @classmethod
    def _fov(cls, v: tuple[float, float]) -> tuple[float, float]:
        if max(v) >= 180.0:
            raise ValueError(f"fov_deg={v}; expected each angle < 180 deg")
        return v

    @model_validator(mode="after")
    def _derive_transition(self) -> SensorConfig:
        if self.transition_range_m is None:
            k, s = self.triangulation.noise_k_per_m, self.tof.noise_sigma_m
            r = math.sqrt(s / k) if k > 0 and s > 0 else 7.0
            # validate_assignment would recurse; set the derived value directly.
            object.__setattr__(self, "transition_range_m", min(r, self.triangulation.max_range_m))
        return self


class FlashLidarConfig(StrictModel):
    """Flash LiDAR of seed 003 section 3.1: a grid of pixels captured at one instant."""

    rows: Annotated[int, Field(ge=2, le=4096)] = 500
    cols: Annotated[int, Field(ge=2, le=4096)] = 500
    fov_deg: tuple[PositiveFloat, PositiveFloat] = (20.0, 20.0)
    range_error_m: NonNegFloat = 0.01
    error_model: Literal["uniform", "gaussian"] = "uniform"
    min_range_m: NonNegFloat = 0.5
    max_range_m: PositiveFloat = 150.0
    grazing_limit_deg: Annotated[float, Field(gt=0, le=90)] = 85.0


# ---------------------------------------------------------------------------------------------
# Estimators and the TriDAR pipeline
# ---------------------------------------------------------------------------------------------
class ICPConfig(StrictModel):
    """ICP tracking settings (seed 000 section 3.2)."""

    method: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    model_points: Annotated[int, Field(ge=100)] = 20_000
    max_iterations: Annotated[int, Field(ge=1)] = 50
    max_correspondence_m: PositiveFloat = Field(0.5, description="initial gating distance")
    min_correspondence_m: PositiveFloat = Field(0.02, description="floor of the adaptive gate")
    trim_fraction: Annotated[float, Field(ge=0, lt=1)] = 0.1
    gate_median_factor: NonNegFloat = Field(
        6.0, description="each iteration, drop matches farther than this many times the median "
        "match distance (never below the gate floor; 0: off): stray returns in front of or behind "
        "the surface (1 % of a frame) are rejected however close the pose already is"
    )
    robust_kernel: Literal["none", "huber", "tukey", "cauchy"] = "huber"
    translation_tol_m: PositiveFloat = 1e-5
    rotation_tol_rad: PositiveFloat = 1e-6
    residual_tol: NonNegFloat = 1e-7
    step_tol_sigma: NonNegFloat = Field(
        0.05,
        description="fine phase: converged once a step is below this many sigmas of the frame's "
        "own information (Mahalanobis length; 0 disables)",
    )
    time_budget_s: PositiveFloat | None = None
    min_points: Annotated[int, Field(ge=6)] = 10
    kernel_scale: PositiveFloat = Field(
        2.5, description="robust kernel threshold in units of the residual's noise sigma"
    )
    noise_floor_fraction: NonNegFloat = Field(
        0.2, description="residual noise floor as a fraction of the range sigma (grazing rays)"
    )
    degeneracy_ratio: Annotated[float, Field(gt=0, lt=1)] = Field(
        1e-4, description="information eigenvalue ratio below which a direction is unobservable"
    )
    min_direction_support: NonNegFloat = Field(
        0.0, description="effective number of points that must carry a direction's information "
        "for it to count as observed (0: off)"
    )
    edge_ambiguity_sigmas: NonNegFloat = Field(
        2.5, description="a grazing match lying within this many range sigmas (plus the model "
        "spacing) of a differently oriented face informs no direction: edge mixing, which held "
        "a flat face's wrong in-plane pose with confidence; the pipeline's outline refinement "
        "then observes those axes from the scan's outline (0: off)"
    )
    model_noise_fraction: NonNegFloat = Field(
        0.1, description="model resolution error as a fraction of the model sample spacing"
    )
    plane_candidates: Annotated[int, Field(ge=1, le=16)] = Field(
        3, description="fine phase: nearest samples among which the best-fitting plane is matched"
    )
    back_facing_cos: Annotated[float, Field(ge=-1, le=1)] = Field(
        0.3, description="drop matches whose model normal . ray direction exceeds this (back faces)"
    )
    match_along_rays: bool = Field(
        False, description="match each point to the face its measured ray crosses (unbiased near "
        "edges; PAH turns it on). Off by default in tracking: closed-loop docking on the iss_port "
        "model was worse with it at all ranges (the demo's max error 92 cm / 17 deg vs 15 cm / 2 "
        "deg); its missions turn it on for triangulation data (icp_triangulation)"
    )


class PAHConfig(StrictModel):
    """Polygonal aspect hashing acquisition (seed 000 section 3.1)."""

    model_points: Annotated[int, Field(ge=20)] = 400
    length_bin_m: PositiveFloat = 0.05
    length_tolerance_m: PositiveFloat = 0.05
    polygon_size: Annotated[int, Field(ge=4, le=6)] = 4
    max_polygons: Annotated[int, Field(ge=1)] = 40
    max_candidates: Annotated[int, Field(ge=1)] = 20_000
    fit_inlier_m: PositiveFloat = 0.05
    precheck_points: Annotated[int, Field(ge=10)] = 60
    accept_fitness: UnitFloat = Field(
        0.98, description="stop once a hypothesis has this fraction of the scan within 3 sigma"
    )


class CorridorConfig(StrictModel):
    """Approach corridor: a cone about the port axis plus attitude and range bounds."""

    half_angle_deg: Annotated[float, Field(gt=0, le=180)] = 15.0
    attitude_tolerance_deg: Annotated[float, Field(gt=0, le=180)] = 20.0
    min_range_m: NonNegFloat = 0.0
    max_range_m: PositiveFloat = 1000.0


class IntegrityConfig(StrictModel):
    """What a published pose promises (:mod:`perception.integrity`)."""

    risk: Annotated[float, Field(gt=0, lt=0.5, allow_inf_nan=False)] = Field(
        1e-5, description="probability that the port position error exceeds the protection level"
    )
    alert_limit_m: PositiveFloat = Field(
        0.08, description="tolerable port position error [m] inside alert_limit_range_m; a pose "
        "whose protection level exceeds the alert limit is published degraded"
    )
    alert_limit_range_m: PositiveFloat = Field(
        5.0, description="beyond this range [m] the alert limit grows in proportion to the range"
    )
    bias_m: NonNegFloat = Field(
        0.005, description="1-sigma of the registrations' time-correlated position error at the "
        "port [m] (model error, ICP bias over a stretch of similar views): a filter that averages "
        "frames cannot average it away, so it is added to the published position covariance"
    )
    bias_rad: NonNegFloat = Field(
        0.001, description="the same correlated error growing with range [rad]: 1-sigma "
        "max(bias_m, bias_rad * range) (beam footprint, TOF noise over a far target; a generated "
        "boxes-and-booms target was 4-12 cm off at 15-30 m under a 3 cm protection level)"
    )
    confirm_frames: Annotated[int, Field(ge=1)] = Field(
        3, description="accepted frames before a new track's pose may be published valid"
    )


class ScanPlanConfig(StrictModel):
    """Observability-aware choice of the tracking region (:mod:`perception.observability`)."""

    mode: Literal["range", "observability"] = Field(
        "observability", description="range: seed 000's regions by range; observability: the candidate "
        "region with the smallest predicted bound at the port (range strategy as the default)"
    )
    period_s: PositiveFloat = Field(
        1.0, description="a plan stands this long [s]; re-planned only while registrations leave "
        "axes unobserved, or to return to the range strategy's region"
    )
    rays: Annotated[int, Field(ge=20, le=5000)] = Field(300, description="rays per predicted scan")
    switch_factor: Annotated[float, Field(ge=1, allow_inf_nan=False)] = Field(
        1.5, description="leave the range strategy's region only for a bound this many times smaller"
    )
    attitude_lever_m: NonNegFloat = Field(0.5, description="attitude bound weight in the score [m/rad]")
    edge_ambiguity_sigmas: NonNegFloat = Field(2.5, description="as icp.edge_ambiguity_sigmas")
    min_support: NonNegFloat = Field(5.0, description="as icp.min_direction_support (frame points)")
    outline: bool = Field(True, description="count the outline information the pipeline's "
                          "outline refinement adds (pipeline.outline_refinement)")


class PipelineConfig(StrictModel):
    """The mission configuration database of seed 000 section 3.3/5.3: modes, strategies by range."""

    bearing_to_search_range_m: PositiveFloat = 200.0
    search_to_bearing_range_m: PositiveFloat = 250.0
    roi_whole_above_m: PositiveFloat = Field(20.0, description="whole structure beyond this range")
    roi_port_below_m: PositiveFloat = Field(5.0, description="docking port only below this range")
    loss_of_track_frames: Annotated[int, Field(ge=1)] = 3
    max_inlier_rmse_factor: PositiveFloat = 4.0
    min_fitness: UnitFloat = 0.5
    acquire_min_fitness: UnitFloat = Field(
        0.8, description="a search pose starts a track only if this fraction of the scan fits it"
    )
    max_jump_m: PositiveFloat = 0.5
    max_jump_deg: PositiveFloat = 10.0
    restart_period_s: PositiveFloat | None = None
    restart_inhibit_range_m: NonNegFloat = Field(
        3.0, description="no planned restart while the estimated docking port is closer than this "
        "[m]: a track dropped on purpose seconds before contact leaves the controller a freshly "
        "reacquired state at the envelope's edge (0: restarts at any range)"
    )
    tracking_latency_s: NonNegFloat = 0.09
    search_latency_s: NonNegFloat = 1.0
    bearing_latency_s: NonNegFloat = 0.02
    frame_rate_hz: PositiveFloat = 5.0
    use_corridor: bool = True
    corridor: CorridorConfig = CorridorConfig()
    icp_triangulation: ICPConfig | None = Field(
        None, description="tracker settings on triangulation data (default: icp)"
    )
    icp: ICPConfig = ICPConfig()
    pah: PAHConfig = PAHConfig()
    process_noise_accel: PositiveFloat = Field(
        0.05, description="white relative acceleration [m/s^2/sqrt(Hz)]: covers chaser thrust"
    )
    process_noise_angacc: PositiveFloat = Field(0.005, description="[rad/s^2/sqrt(Hz)]")
    symmetry_check_period_s: PositiveFloat | None = Field(
        None,
        description="ambiguity monitor: every this many seconds of tracking, ICP from each "
        "near-symmetric turn of the tracked pose and switch to one that explains the points "
        "clearly better (None: off)",
    )
    symmetry_switch_checks: Annotated[int, Field(ge=1)] = Field(
        3, description="checks in a row that must prefer the same turn before switching to it"
    )
    symmetry_margin: PositiveFloat = Field(
        0.01, description="lead in PAH score (likelihood minus twice the unexplained fraction) to switch"
    )
    ego_motion: bool = Field(
        False,
        description="fuse the host's gyro and accelerometer (perception.filter.EgoMotion) into the "
        "relative-motion filter, so that the chaser's own rotation and thrust are not process noise",
    )
    target_rotation: Literal["constant_rate", "torque_free"] = Field(
        "constant_rate",
        description="filter model of the target's inertial rate: constant, or Euler's torque-free "
        "equations with the target model's inertia (a tumbling target)",
    )
    measurement_floor_m: NonNegFloat = Field(
        0.01, description="added to the registration's position sigma (model error, TOF bias)"
    )
    measurement_floor_deg: NonNegFloat = Field(0.3, description="added attitude sigma [deg]")
    reacquire_window_s: NonNegFloat = Field(
        3.0, description="after a loss, search first tries ICP from the lost track's prediction"
    )
    filter_reinit_frames: Annotated[int, Field(ge=1)] = Field(
        2, description="good registrations rejected by the filter gate in a row before re-init"
    )
    integrity: IntegrityConfig = IntegrityConfig()
    outline_refinement: bool = Field(
        True, description="when ICP leaves axes unobserved, refine the pose with the scan's "
        "outline (samples that returned next to samples that did not)"
    )
    scan_plan: ScanPlanConfig = ScanPlanConfig()
    fine_only_tracking: bool = Field(
        True, description="on an established track (rates estimated, the last frames accepted) "
        "ICP starts from the filter's prediction in its fine phase, without the coarse phase "
        "(one correspondence search fewer per frame)"
    )


# ---------------------------------------------------------------------------------------------
# World and environment
# ---------------------------------------------------------------------------------------------
class OrbitConfig(StrictModel):
    """The target's circular reference orbit."""

    altitude_m: PositiveFloat = 400_000.0
    inclination_deg: Annotated[float, Field(ge=0, le=180)] = 51.6
    model: Literal["cw", "nonlinear"] = "cw"
    j2: bool = False


class TargetAttitudeConfig(StrictModel):
    """Target attitude motion: held in LVLH, held inertially, or tumbling torque-free."""

    mode: Literal["lvlh_hold", "inertial_hold", "tumble"] = "lvlh_hold"
    spin_rate_deg_s: NonNegFloat = 0.0
    nutation_deg: Annotated[float, Field(ge=0, le=90)] = 0.0
    spin_axis: Literal["max", "min"] = "max"
    initial_rpy_deg: Vec3 = (0.0, 0.0, 0.0)


class ChaserConfig(StrictModel):
    """Chaser spacecraft: mass, propulsion, attitude mode and mounted frames."""

    dry_mass_kg: PositiveFloat = 400.0
    propellant_kg: NonNegFloat = 50.0
    isp_s: PositiveFloat = 220.0
    max_thrust_n: PositiveFloat = 20.0
    max_torque_nm: PositiveFloat = 2.0
    thrust_frame: Literal["lvlh", "body"] = "body"
    attitude: Literal["ideal", "controlled"] = "ideal"
    sensor_position_m: Vec3 = Field(
        (0.45, 0.2, -1.5),
        description="TriDAR mount [m], chaser body: set back and aimed so that at contact the "
        "docking target and guide petals stay in its 30 deg field of view",
    )
    sensor_rpy_deg: Vec3 = (0.0, 0.0, 0.0)
    dock_position_m: Vec3 = (0.0, 0.0, 0.6)
    hull_radius_m: PositiveFloat = 0.5
    gyro_noise_deg_s: NonNegFloat = Field(
        0.0, description="1-sigma white noise of each gyro reading [deg/s] (the observation's "
        "gyro and the pipeline's ego-motion see the same reading)"
    )
    gyro_bias_deg_s: NonNegFloat = Field(
        0.0, description="1-sigma of the gyro's constant bias per axis, drawn at reset [deg/s]"
    )
    accel_noise_m_s2: NonNegFloat = Field(
        0.0, description="1-sigma white noise of each accelerometer reading [m/s^2]"
    )


class DynamicsConfig(StrictModel):
    """Relative translational and rotational dynamics."""

    orbit: OrbitConfig = OrbitConfig()
    target_attitude: TargetAttitudeConfig = TargetAttitudeConfig()
    chaser: ChaserConfig = ChaserConfig()


class DockingEnvelopeConfig(StrictModel):
    """IDSS-like capture envelope (all relative, at contact)."""

    axial_speed_min_m_s: NonNegFloat = 0.05
    axial_speed_max_m_s: PositiveFloat = 0.10
    lateral_offset_max_m: PositiveFloat = 0.10
    lateral_speed_max_m_s: PositiveFloat = 0.04
    misalignment_max_deg: PositiveFloat = 4.0
    angular_rate_max_deg_s: PositiveFloat = 0.15

    @model_validator(mode="after")
    def _speeds(self) -> DockingEnvelopeConfig:
        if self.axial_speed_min_m_s > self.axial_speed_max_m_s:
            raise ValueError(
                f"axial_speed_min_m_s={self.axial_speed_min_m_s} exceeds "
                f"axial_speed_max_m_s={self.axial_speed_max_m_s}"
            )
        return self


class RewardConfig(StrictModel):
    """Weights of the reward terms (each term is reported in ``info`` as ``reward_<name>``).

    ``progress`` and ``lateral`` are potential-based shaping (the decrease of the dock-to-port
    distance and of the offset from the port axis, per metre), so they change how fast a policy
    learns, not which policy is best. ``speed_limit`` (closing faster than the limit) and
    ``speed_profile`` (closing speed off the reference profile, which ends in the middle of the
    envelope's axial-speed band) are per m/s, the first per step and the second per second of
    simulated time; ``time`` is per second; ``fuel`` per kg.
    ``collision`` is the penalty for hitting the hull or slamming the port; a port contact just
    outside the envelope costs ``collision * min(1, near_miss + excess)``, where ``excess`` is the
    largest relative violation of an envelope limit, so that a near miss is told from a crash.
    """

    progress: FiniteFloat = 1.0
    lateral: FiniteFloat = 2.0
    alignment: FiniteFloat = 0.1
    speed_limit: FiniteFloat = 1.0
    speed_profile: FiniteFloat = 1.0
    time: FiniteFloat = 0.02
    fuel: FiniteFloat = 10.0
    success: FiniteFloat = 100.0
    collision: FiniteFloat = 100.0
    near_miss: Annotated[float, Field(ge=0, le=1)] = 0.3
    corridor: FiniteFloat = 50.0


class InitialStateConfig(StrictModel):
    """Starting relative state (along the port axis) and its dispersion."""

    range_m: PositiveFloat = 30.0
    range_dispersion_m: NonNegFloat = 2.0
    range_min_m: PositiveFloat | None = Field(
        None, description="lower clip of the dispersed range [m] (default: half of range_m)"
    )
    lateral_dispersion_m: NonNegFloat = 0.5
    velocity_dispersion_m_s: NonNegFloat = 0.005
    closing_speed_m_s: NonNegFloat = 0.0


class EnvConfig(StrictModel):
    """Gymnasium environment settings."""

    perception: Literal["tridar", "truth", "truth+noise"] = "tridar"
    frame_period_s: PositiveFloat = 0.2
    frame_skip: Annotated[int, Field(ge=1)] = 1
    max_episode_steps: Annotated[int, Field(ge=1)] = 2000
    max_range_m: PositiveFloat = 100.0
    corridor_half_angle_deg: Annotated[float, Field(gt=0, le=180)] | None = None
    truth_noise_position_m: NonNegFloat = 0.01
    truth_noise_velocity_m_s: NonNegFloat = 0.002
    truth_noise_attitude_deg: NonNegFloat = 0.5
    truth_noise_rate_deg_s: NonNegFloat = 0.05
    truth_noise_correlation_s: NonNegFloat = Field(
        0.0, description="time constant of the truth+noise errors (first-order Gauss-Markov; 0: "
        "independent each step). The pipeline's errors persist for seconds, not one frame"
    )
    truth_noise_reference: Literal["port", "center_of_mass"] = Field(
        "port", description="point of the target where the truth+noise position error is applied: "
        "the docking port (as the pipeline, which observes and filters about the port) or the "
        "centre of mass (then attitude errors also move the port by the lever arm)"
    )
    speed_limit_gain_s: PositiveFloat = Field(0.02, description="v_max = v0 + gain * range")
    speed_limit_floor_m_s: PositiveFloat = 0.08
    speed_profile_gain_s: NonNegFloat = Field(
        0.01, description="reference closing speed v_ref = envelope mid-speed + gain * distance "
        "(reward.speed_profile)"
    )
    speed_profile_max_m_s: PositiveFloat = Field(0.2, description="cap of the reference closing speed")
    initial: InitialStateConfig = InitialStateConfig()
    envelope: DockingEnvelopeConfig = DockingEnvelopeConfig()
    reward: RewardConfig = RewardConfig()
    point_cloud_size: Annotated[int, Field(ge=1)] = 1024


class MissionConfig(StrictModel):
    """A whole scenario: target, sensor, estimators, dynamics and environment."""

    name: str = "mission"
    description: str = ""
    target: TargetConfig = TargetConfig()
    sensor: SensorConfig = SensorConfig()
    flash: FlashLidarConfig = FlashLidarConfig()
    pipeline: PipelineConfig = PipelineConfig()
    dynamics: DynamicsConfig = DynamicsConfig()
    env: EnvConfig = EnvConfig()


# ---------------------------------------------------------------------------------------------
# Loading and saving
# ---------------------------------------------------------------------------------------------
M = TypeVar("M", bound=BaseModel)


def _format_errors(exc: ValidationError, source: str) -> str:
    lines = [f"invalid configuration in {source}:"]
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "<root>"
        value = err.get("input")
        if err["type"] == "extra_forbidden":
            lines.append(f"  {loc}: unknown key (value {value!r}); check the spelling")
        else:
            lines.append(f"  {loc}: got {value!r}; expected {err['msg'].lower()}")
    return "\n".join(lines)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping with ``yaml.safe_load``; an empty file is an empty mapping."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {p} is not valid YAML: {exc}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} holds a {type(data).__name__}; expected a mapping")
    return data


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Merge overrides into a nested mapping. Keys nest with ``__`` or ``.`` (``sensor__tof__bias_m``);
    a mapping value is merged recursively."""
    out = _deep_copy(data)
    for key, value in overrides.items():
        parts = key.replace(".", "__").split("__")
        node = out
        for part in parts[:-1]:
            nxt = node.get(part)
            if not isinstance(nxt, dict):
                nxt = {}
                node[part] = nxt
            node = nxt
        leaf = parts[-1]
        if isinstance(value, dict) and isinstance(node.get(leaf), dict):
            node[leaf] = apply_overrides(node[leaf], value)
        else:
            node[leaf] = value
    return out


def flatten_overrides(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> ``{"a__b__c": value}`` overrides (the inverse of :func:`apply_overrides`)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}__{k}" if prefix else k
        if isinstance(v, dict):
            out.update(flatten_overrides(v, key))
        else:
            out[key] = v
    return out


def _deep_copy(d: dict[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, dict) else v for k, v in d.items()}


def config_path(path: str | Path, kind: str = "missions") -> Path:
    """A YAML path as given, or a bare name (``"final_approach"``) looked up in ``configs/<kind>``."""
    p = Path(path)
    if not p.suffix and not p.exists():
        return CONFIG_DIR / kind / f"{p}.yaml"
    return p


def load_config(
    path: str | Path | None = None, model: type[M] = MissionConfig, **overrides: Any  # type: ignore[assignment]
) -> M:
    """Load and validate a config file (or just the defaults when ``path`` is None).

    Args:
        path: YAML file; a bare name such as ``"final_approach"`` is looked up in ``configs/missions``.
        model: the pydantic model the file describes (default :class:`MissionConfig`).
        **overrides: values that replace the file's, nested with ``__`` (``env__frame_skip=2``).

    Raises:
        ConfigError: a missing or unreadable file, unknown keys, or values out of range; the message
            names each field, its value and what was expected.
    """
    data: dict[str, Any] = {}
    source = "defaults"
    if path is not None:
        p = config_path(path)
        data = load_yaml(p)
        source = str(p)
    if overrides:
        data = apply_overrides(data, overrides)
        source += f" (with overrides {sorted(overrides)})"
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_errors(exc, source)) from None


def save_config(cfg: BaseModel, path: str | Path) -> Path:
    """Write the resolved config (every default filled in) as YAML next to a result."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    return p


def shipped_configs() -> list[Path]:
    """Every YAML file under ``configs/``."""
    return sorted(CONFIG_DIR.rglob("*.yaml"))
