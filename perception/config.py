"""Configuration: pydantic models, one per concern, read from YAML with a bounded safe loader.

This is the one place where configuration is defined (``perception`` cannot import ``tridar_env``,
so the models of every concern live here and both packages use them). A mission YAML file has the
shape of :class:`MissionConfig`; every section is optional and falls back to documented physical
defaults. Unknown keys and bad values are rejected with a one-line message naming the field, the
value (cut short) and what was expected. Reading is bounded whatever the file holds: size, nesting
and alias expansion have limits, duplicate keys are refused. A number field takes an int or a
float, never a bool or a string, and every physical quantity has an upper bound.

Example:
    >>> from perception.config import load_config
    >>> cfg = load_config("configs/missions/final_approach.yaml", sensor__tof__noise_sigma_m=0.03)
    >>> cfg.sensor.tof.noise_sigma_m
    0.03
"""

from __future__ import annotations

import math
import os
import re
import reprlib
import stat
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    ValidationError,
    model_validator,
)
from pydantic_core import PydanticCustomError

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
    "InitialStateConfig",
    "IntegrityConfig",
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
    "parse_yaml",
    "resolve_config",
    "save_config",
    "shipped_configs",
    "short_repr",
]

#: Folder of the shipped YAML files (``configs/`` at the repository root).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"

#: Upper bounds of the physical quantities: generous for any rendezvous or docking scenario, and
#: small enough that their squares and products stay finite (``initial.range_m: 1e300`` made the
#: reward NaN). A value above one is refused naming the field and the bound.
MAX_RANGE_M = 1e5  # relative distances and sensor ranges [m]
MAX_SIZE_M = 1e3  # positions on the vehicles, radii, gates and tolerances [m]
MAX_SIGMA_M = 100.0  # noise sigmas and biases [m]
MAX_ALTITUDE_M = 1e8
MAX_PERIOD_S = 86_400.0  # periods and windows [s]
MAX_FRAME_PERIOD_S = 60.0  # one sensor frame (a control step) and the latencies [s]
MAX_SPEED_M_S = 100.0
MAX_ACCEL_M_S2 = 100.0
MAX_RATE_DEG_S = 360.0
MAX_MASS_KG = 1e6
MAX_FORCE = 1e5  # thrust [N] and torque [N m]
MAX_ISP_S = 1e5
MAX_FACTOR = 1e6  # dimensionless factors and reward weights
MAX_COUNT = 1_000_000_000  # frame counters and candidate budgets


def _number(value: Any) -> Any:
    """Refuse what pydantic's lax mode would read as a number but is not one: ``True`` is not
    1 s, and ``"1.0"`` is a string (a YAML value in quotes), not a number."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise PydanticCustomError(
            "number_type", "a number, not {kind}", {"kind": f"a {type(value).__name__}"}
        )
    return value


#: Any finite number (an int is a float); the quantities below add their bounds.
Float = Annotated[float, BeforeValidator(_number), Field(allow_inf_nan=False)]
Int = Annotated[int, BeforeValidator(_number)]
PositiveFloat = Annotated[Float, Field(gt=0, le=MAX_FACTOR)]
NonNegFloat = Annotated[Float, Field(ge=0, le=MAX_FACTOR)]
UnitFloat = Annotated[Float, Field(ge=0, le=1)]
FiniteFloat = Annotated[Float, Field(ge=-MAX_FACTOR, le=MAX_FACTOR)]
Weight = FiniteFloat
Range = Annotated[Float, Field(gt=0, le=MAX_RANGE_M)]
NonNegRange = Annotated[Float, Field(ge=0, le=MAX_RANGE_M)]
Size = Annotated[Float, Field(gt=0, le=MAX_SIZE_M)]
Offset = Annotated[Float, Field(ge=-MAX_SIZE_M, le=MAX_SIZE_M)]
Vec3 = tuple[Offset, Offset, Offset]
Angle = Annotated[Float, Field(ge=-360, le=360)]
Angles3 = tuple[Angle, Angle, Angle]
FieldOfView = Annotated[Float, Field(gt=0, lt=180)]
SmallAngle = Annotated[Float, Field(ge=0, le=math.pi)]
Sigma = Annotated[Float, Field(ge=0, le=MAX_SIGMA_M)]
Period = Annotated[Float, Field(gt=0, le=MAX_PERIOD_S)]
NonNegPeriod = Annotated[Float, Field(ge=0, le=MAX_PERIOD_S)]
FramePeriod = Annotated[Float, Field(gt=0, le=MAX_FRAME_PERIOD_S)]
Latency = Annotated[Float, Field(ge=0, le=MAX_FRAME_PERIOD_S)]
Speed = Annotated[Float, Field(gt=0, le=MAX_SPEED_M_S)]
NonNegSpeed = Annotated[Float, Field(ge=0, le=MAX_SPEED_M_S)]
Rate = Annotated[Float, Field(ge=0, le=MAX_RATE_DEG_S)]
NonNegMass = Annotated[Float, Field(ge=0, le=MAX_MASS_KG)]
Force = Annotated[Float, Field(gt=0, le=MAX_FORCE)]


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

    name: str = Field(
        "cubesat", max_length=4096,
        description="library name (cubesat, cygnss, iss_port, hubble) or mesh path",
    )
    scale: Annotated[Float, Field(gt=0, le=1000)] = 1.0
    port_position_m: Vec3 | None = None
    port_axis: Vec3 | None = None
    mass_kg: Annotated[Float, Field(ge=0.1, le=MAX_MASS_KG)] | None = None
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

    noise_k_per_m: UnitFloat = Field(5e-4, description="sigma = k * r^2 [1/m]")
    min_range_m: NonNegRange = 0.3
    max_range_m: Range = 20.0
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

    noise_sigma_m: Sigma = 0.025
    bias_m: Annotated[Float, Field(ge=-MAX_SIGMA_M, le=MAX_SIGMA_M)] = 0.005
    max_range_ref_m: Range = 3000.0
    power_fraction: Annotated[Float, Field(gt=0, le=1)] = 1.0
    saturation_range_m: NonNegRange = 2.0
    saturation_reflectivity: UnitFloat = 0.3
    min_range_m: NonNegRange = 0.5


class BeamConfig(StrictModel):
    """Laser footprint: full-angle divergence and the sub-rays that sample it."""

    divergence_rad: SmallAngle = 5e-4
    subrays: Annotated[Int, Field(ge=1, le=64)] = 5
    mixed_range_tolerance_m: Size = Field(
        0.05, description="sub-ray ranges spread more than this -> mixed pixel (edge)"
    )


class PointingConfig(StrictModel):
    """Scanning-mirror pointing: angle quantisation and random jitter."""

    resolution_rad: SmallAngle = 2e-5
    jitter_rad: SmallAngle = 1e-5


class MaterialResponseConfig(StrictModel):
    """How surfaces return light: grazing dropout and the specular acceptance cone."""

    grazing_limit_deg: Annotated[Float, Field(gt=0, le=90)] = 80.0
    specular_cone_deg: Annotated[Float, Field(gt=0, le=90)] = 5.0


class OccluderConfig(StrictModel):
    """A sphere in the sensor frame that blocks rays (an arm, a boom, a visiting vehicle)."""

    center_m: Vec3
    radius_m: Size


class FaultsConfig(StrictModel):
    """Fault and environment injection (all off by default)."""

    dropout_prob: UnitFloat = 0.0
    spurious_prob: UnitFloat = Field(0.0, description="per-sample probability of a stray-light return")
    blackout_start_frame: Annotated[Int, Field(ge=0, le=MAX_COUNT)] | None = None
    blackout_frames: Annotated[Int, Field(ge=0, le=MAX_COUNT)] = 0
    occluder: OccluderConfig | None = None


class ScanConfig(StrictModel):
    """Scan pattern selection and mirror limits."""

    pattern: Literal["lissajous", "rosette", "spiral", "raster"] = "rosette"
    n_points: Annotated[Int, Field(ge=4, le=200_000)] = 1000
    sample_rate_hz: Annotated[Float, Field(gt=0, le=1e9)] = 10_000.0
    phase_step: Annotated[Float, Field(ge=-2 * math.pi, le=2 * math.pi)] = Field(
        0.37, description="pattern phase advance per frame [rad]"
    )
    max_mirror_accel_rad_s2: Annotated[Float, Field(gt=0, le=1e9)] = Field(
        200_000.0,
        description="optical-angle limit; ~1,000-point patterns over 30 deg in 0.1 s need ~1.5e5",
    )


class SensorConfig(StrictModel):
    """The TriDAR hybrid scanner (seed 000 section 4)."""

    fov_deg: tuple[FieldOfView, FieldOfView] = (30.0, 30.0)
    triangulation: TriangulationConfig = TriangulationConfig()
    tof: TOFConfig = TOFConfig()
    transition_range_m: Range | None = Field(
        None, description="triangulation/TOF switch; default: where their noise models cross"
    )
    beam: BeamConfig = BeamConfig()
    pointing: PointingConfig = PointingConfig()
    material: MaterialResponseConfig = MaterialResponseConfig()
    faults: FaultsConfig = FaultsConfig()
    scan: ScanConfig = ScanConfig()

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

    rows: Annotated[Int, Field(ge=2, le=4096)] = 500
    cols: Annotated[Int, Field(ge=2, le=4096)] = 500
    fov_deg: tuple[FieldOfView, FieldOfView] = (20.0, 20.0)
    range_error_m: Sigma = 0.01
    error_model: Literal["uniform", "gaussian"] = "uniform"
    min_range_m: NonNegRange = 0.5
    max_range_m: Range = 150.0
    grazing_limit_deg: Annotated[Float, Field(gt=0, le=90)] = 85.0


# ---------------------------------------------------------------------------------------------
# Estimators and the TriDAR pipeline
# ---------------------------------------------------------------------------------------------
class ICPConfig(StrictModel):
    """ICP tracking settings (seed 000 section 3.2)."""

    method: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    model_points: Annotated[Int, Field(ge=100, le=2_000_000)] = 20_000
    max_iterations: Annotated[Int, Field(ge=1, le=10_000)] = 50
    max_correspondence_m: Size = Field(0.5, description="initial gating distance")
    min_correspondence_m: Size = Field(0.02, description="floor of the adaptive gate")
    trim_fraction: Annotated[Float, Field(ge=0, lt=1)] = 0.1
    gate_median_factor: NonNegFloat = Field(
        6.0, description="each iteration, drop matches farther than this many times the median "
        "match distance (never below the gate floor; 0: off): stray returns in front of or behind "
        "the surface (1 % of a frame) are rejected however close the pose already is"
    )
    robust_kernel: Literal["none", "huber", "tukey", "cauchy"] = "huber"
    translation_tol_m: Size = 1e-5
    rotation_tol_rad: SmallAngle = 1e-6
    residual_tol: NonNegFloat = 1e-7
    step_tol_sigma: NonNegFloat = Field(
        0.05,
        description="fine phase: converged once a step is below this many sigmas of the frame's "
        "own information (Mahalanobis length; 0 disables)",
    )
    time_budget_s: Annotated[Float, Field(gt=0, le=3600)] | None = None
    min_points: Annotated[Int, Field(ge=6, le=MAX_COUNT)] = 10
    kernel_scale: PositiveFloat = Field(
        2.5, description="robust kernel threshold in units of the residual's noise sigma"
    )
    noise_floor_fraction: NonNegFloat = Field(
        0.2, description="residual noise floor as a fraction of the range sigma (grazing rays)"
    )
    degeneracy_ratio: Annotated[Float, Field(gt=0, lt=1)] = Field(
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
    plane_candidates: Annotated[Int, Field(ge=1, le=16)] = Field(
        3, description="fine phase: nearest samples among which the best-fitting plane is matched"
    )
    back_facing_cos: Annotated[Float, Field(ge=-1, le=1)] = Field(
        0.3, description="drop matches whose model normal . ray direction exceeds this (back faces)"
    )
    match_along_rays: StrictBool = Field(
        False, description="match each point to the face its measured ray crosses (unbiased near "
        "edges; PAH turns it on). Off by default in tracking: closed-loop docking on the iss_port "
        "model was worse with it at all ranges (the demo's max error 92 cm / 17 deg vs 15 cm / 2 "
        "deg); its missions turn it on for triangulation data (icp_triangulation)"
    )


class PAHConfig(StrictModel):
    """Polygonal aspect hashing acquisition (seed 000 section 3.1)."""

    model_points: Annotated[Int, Field(ge=20, le=1_000_000)] = 400
    length_bin_m: Size = 0.05
    length_tolerance_m: Size = 0.05
    polygon_size: Annotated[Int, Field(ge=4, le=6)] = 4
    max_polygons: Annotated[Int, Field(ge=1, le=10_000)] = 40
    max_candidates: Annotated[Int, Field(ge=1, le=MAX_COUNT)] = 20_000
    fit_inlier_m: Size = 0.05
    precheck_points: Annotated[Int, Field(ge=10, le=100_000)] = 60
    accept_fitness: UnitFloat = Field(
        0.98, description="stop once a hypothesis has this fraction of the scan within 3 sigma"
    )


class CorridorConfig(StrictModel):
    """Approach corridor: a cone about the port axis plus attitude and range bounds."""

    half_angle_deg: Annotated[Float, Field(gt=0, le=180)] = 15.0
    attitude_tolerance_deg: Annotated[Float, Field(gt=0, le=180)] = 20.0
    min_range_m: NonNegRange = 0.0
    max_range_m: Range = 1000.0


class IntegrityConfig(StrictModel):
    """What a published pose promises (:mod:`perception.pipeline.integrity`)."""

    risk: Annotated[Float, Field(gt=0, lt=0.5)] = Field(
        1e-5, description="probability that the port position error exceeds the protection level"
    )
    alert_limit_m: Size = Field(
        0.08, description="tolerable port position error [m] inside alert_limit_range_m; a pose "
        "whose protection level exceeds the alert limit is published degraded"
    )
    alert_limit_range_m: Range = Field(
        5.0, description="beyond this range [m] the alert limit grows in proportion to the range"
    )
    bias_m: Sigma = Field(
        0.005, description="1-sigma of the registrations' time-correlated position error at the "
        "port [m] (model error, ICP bias over a stretch of similar views): a filter that averages "
        "frames cannot average it away, so it is added to the published position covariance"
    )
    bias_rad: Annotated[Float, Field(ge=0, le=1)] = Field(
        0.001, description="the same correlated error growing with range [rad]: 1-sigma "
        "max(bias_m, bias_rad * range) (beam footprint, TOF noise over a far target; a generated "
        "boxes-and-booms target was 4-12 cm off at 15-30 m under a 3 cm protection level)"
    )
    confirm_frames: Annotated[Int, Field(ge=1, le=10_000)] = Field(
        3, description="accepted frames before a new track's pose may be published valid"
    )
    ambiguity_check_period_s: Period | None = Field(
        1.0, description="twin monitor: every this many seconds of tracking (and on each new "
        "track's first frames), ICP from each near-symmetric turn of the tracked pose; while one "
        "explains the scan about as well (within ambiguity_margin), the protection level grows "
        "by the port's offset between the two poses (None: off)"
    )
    ambiguity_margin: PositiveFloat = Field(
        0.05, description="a twin whose PAH score is within this of the tracked pose's, or "
        "better, makes the pose ambiguous"
    )


class ScanPlanConfig(StrictModel):
    """Observability-aware choice of the tracking region (:mod:`perception.pipeline.observability`)."""

    mode: Literal["range", "observability"] = Field(
        "observability", description="range: seed 000's regions by range; observability: the candidate "
        "region with the smallest predicted bound at the port (range strategy as the default)"
    )
    period_s: Period = Field(
        1.0, description="a plan stands this long [s]; re-planned only while registrations leave "
        "axes unobserved, or to return to the range strategy's region"
    )
    rays: Annotated[Int, Field(ge=20, le=5000)] = Field(300, description="rays per predicted scan")
    switch_factor: Annotated[Float, Field(ge=1, le=MAX_FACTOR)] = Field(
        1.5, description="leave the range strategy's region only for a bound this many times smaller"
    )
    attitude_lever_m: NonNegFloat = Field(0.5, description="attitude bound weight in the score [m/rad]")
    edge_ambiguity_sigmas: NonNegFloat = Field(2.5, description="as icp.edge_ambiguity_sigmas")
    min_support: NonNegFloat = Field(5.0, description="as icp.min_direction_support (frame points)")
    outline: StrictBool = Field(True, description="count the outline information the pipeline's "
                          "outline refinement adds (pipeline.outline_refinement)")


class PipelineConfig(StrictModel):
    """The mission configuration database of seed 000 section 3.3/5.3: modes, strategies by range."""

    bearing_to_search_range_m: Range = 200.0
    search_to_bearing_range_m: Range = 250.0
    roi_whole_above_m: Range = Field(20.0, description="whole structure beyond this range")
    roi_port_below_m: Range = Field(5.0, description="docking port only below this range")
    loss_of_track_frames: Annotated[Int, Field(ge=1, le=MAX_COUNT)] = 3
    max_inlier_rmse_factor: PositiveFloat = 4.0
    min_fitness: UnitFloat = 0.5
    acquire_min_fitness: UnitFloat = Field(
        0.8, description="a search pose starts a track only if this fraction of the scan fits it"
    )
    max_jump_m: Range = 0.5
    max_jump_deg: Annotated[Float, Field(gt=0, le=360)] = 10.0
    restart_period_s: Period | None = None
    restart_inhibit_range_m: NonNegRange = Field(
        3.0, description="no planned restart while the estimated docking port is closer than this "
        "[m]: a track dropped on purpose seconds before contact leaves the controller a freshly "
        "reacquired state at the envelope's edge (0: restarts at any range)"
    )
    tracking_latency_s: Latency = 0.09
    search_latency_s: Latency = 1.0
    bearing_latency_s: Latency = 0.02
    frame_rate_hz: Annotated[Float, Field(gt=0, le=1000)] = 5.0
    use_corridor: StrictBool = True
    corridor: CorridorConfig = CorridorConfig()
    icp_triangulation: ICPConfig | None = Field(
        None, description="tracker settings on triangulation data (default: icp)"
    )
    icp: ICPConfig = ICPConfig()
    pah: PAHConfig = PAHConfig()
    process_noise_accel: Annotated[Float, Field(gt=0, le=MAX_ACCEL_M_S2)] = Field(
        0.05, description="white relative acceleration [m/s^2/sqrt(Hz)]: covers chaser thrust"
    )
    process_noise_angacc: Annotated[Float, Field(gt=0, le=MAX_ACCEL_M_S2)] = Field(
        0.005, description="[rad/s^2/sqrt(Hz)]"
    )
    initial_rate_sigma_deg_s: Annotated[Float, Field(gt=0, le=MAX_RATE_DEG_S)] = Field(
        6.0, description="1-sigma prior on the target's angular rate when a track starts [deg/s] "
        "(a target held in LVLH turns at orbit rate: a tight prior keeps a track's first, "
        "loosely constrained frames from being read as a spin)"
    )
    symmetry_check_period_s: Period | None = Field(
        None,
        description="ambiguity monitor: every this many seconds of tracking, ICP from each "
        "near-symmetric turn of the tracked pose and switch to one that explains the points "
        "clearly better (None: off)",
    )
    symmetry_switch_checks: Annotated[Int, Field(ge=1, le=10_000)] = Field(
        3, description="checks in a row that must prefer the same turn before switching to it"
    )
    symmetry_margin: PositiveFloat = Field(
        0.01, description="lead in PAH score (likelihood minus twice the unexplained fraction) to switch"
    )
    ego_motion: StrictBool = Field(
        False,
        description="fuse the host's gyro and accelerometer (perception.pipeline.filter.EgoMotion) into the "
        "relative-motion filter, so that the chaser's own rotation and thrust are not process noise",
    )
    target_rotation: Literal["constant_rate", "torque_free"] = Field(
        "constant_rate",
        description="filter model of the target's inertial rate: constant, or Euler's torque-free "
        "equations with the target model's inertia (a tumbling target)",
    )
    measurement_floor_m: Sigma = Field(
        0.01, description="added to the registration's position sigma (model error, TOF bias)"
    )
    measurement_floor_deg: Annotated[Float, Field(ge=0, le=180)] = Field(
        0.3, description="added attitude sigma [deg]"
    )
    reacquire_window_s: NonNegPeriod = Field(
        3.0, description="after a loss, search first tries ICP from the lost track's prediction"
    )
    filter_reinit_frames: Annotated[Int, Field(ge=1, le=10_000)] = Field(
        2, description="good registrations rejected by the filter gate in a row before re-init"
    )
    integrity: IntegrityConfig = IntegrityConfig()
    outline_refinement: StrictBool = Field(
        True, description="when ICP leaves axes unobserved, refine the pose with the scan's "
        "outline (samples that returned next to samples that did not)"
    )
    scan_plan: ScanPlanConfig = ScanPlanConfig()
    fine_only_tracking: StrictBool = Field(
        True, description="on an established track (rates estimated, the last frames accepted) "
        "ICP starts from the filter's prediction in its fine phase, without the coarse phase "
        "(one correspondence search fewer per frame)"
    )


# ---------------------------------------------------------------------------------------------
# World and environment
# ---------------------------------------------------------------------------------------------
class OrbitConfig(StrictModel):
    """The target's circular reference orbit."""

    altitude_m: Annotated[Float, Field(gt=0, le=MAX_ALTITUDE_M)] = 400_000.0
    inclination_deg: Annotated[Float, Field(ge=0, le=180)] = 51.6
    model: Literal["cw", "nonlinear"] = "cw"
    j2: StrictBool = False


class TargetAttitudeConfig(StrictModel):
    """Target attitude motion: held in LVLH, held inertially, or tumbling torque-free."""

    mode: Literal["lvlh_hold", "inertial_hold", "tumble"] = "lvlh_hold"
    spin_rate_deg_s: Rate = 0.0
    nutation_deg: Annotated[Float, Field(ge=0, lt=90)] = 0.0
    spin_axis: Literal["max", "min"] = "max"
    initial_rpy_deg: Angles3 = (0.0, 0.0, 0.0)


class ChaserConfig(StrictModel):
    """Chaser spacecraft: mass, propulsion, attitude mode and mounted frames."""

    dry_mass_kg: Annotated[Float, Field(ge=0.1, le=MAX_MASS_KG)] = 400.0
    propellant_kg: NonNegMass = 50.0
    isp_s: Annotated[Float, Field(ge=1, le=MAX_ISP_S)] = 220.0
    max_thrust_n: Force = 20.0
    max_torque_nm: Force = 2.0
    thrust_frame: Literal["lvlh", "body"] = "body"
    attitude: Literal["ideal", "controlled"] = "ideal"
    sensor_position_m: Vec3 = Field(
        (0.45, 0.2, -1.5),
        description="TriDAR mount [m], chaser body: set back and aimed so that at contact the "
        "docking target and guide petals stay in its 30 deg field of view",
    )
    sensor_rpy_deg: Angles3 = (0.0, 0.0, 0.0)
    dock_position_m: Vec3 = (0.0, 0.0, 0.6)
    hull_radius_m: Annotated[Float, Field(ge=0.05, le=MAX_SIZE_M)] = 0.5
    gyro_noise_deg_s: Rate = Field(
        0.0, description="1-sigma white noise of each gyro reading [deg/s] (the observation's "
        "gyro and the pipeline's ego-motion see the same reading)"
    )
    gyro_bias_deg_s: Rate = Field(
        0.0, description="1-sigma of the gyro's constant bias per axis, drawn at reset [deg/s]"
    )
    accel_noise_m_s2: Annotated[Float, Field(ge=0, le=MAX_ACCEL_M_S2)] = Field(
        0.0, description="1-sigma white noise of each accelerometer reading [m/s^2]"
    )


class DynamicsConfig(StrictModel):
    """Relative translational and rotational dynamics."""

    orbit: OrbitConfig = OrbitConfig()
    target_attitude: TargetAttitudeConfig = TargetAttitudeConfig()
    chaser: ChaserConfig = ChaserConfig()


class DockingEnvelopeConfig(StrictModel):
    """IDSS-like capture envelope (all relative, at contact)."""

    axial_speed_min_m_s: NonNegSpeed = 0.05
    axial_speed_max_m_s: Speed = 0.10
    lateral_offset_max_m: Size = 0.10
    lateral_speed_max_m_s: Speed = 0.04
    misalignment_max_deg: Annotated[Float, Field(gt=0, le=180)] = 4.0
    angular_rate_max_deg_s: Annotated[Float, Field(gt=0, le=MAX_RATE_DEG_S)] = 0.15

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

    progress: Weight = 1.0
    lateral: Weight = 2.0
    alignment: Weight = 0.1
    speed_limit: Weight = 1.0
    speed_profile: Weight = 1.0
    time: Weight = 0.02
    fuel: Weight = 10.0
    success: Weight = 100.0
    collision: Weight = 100.0
    near_miss: Annotated[Float, Field(ge=0, le=1)] = 0.3
    corridor: Weight = 50.0


class InitialStateConfig(StrictModel):
    """Starting relative state (along the port axis) and its dispersion."""

    range_m: Range = 30.0
    range_dispersion_m: NonNegRange = 2.0
    range_min_m: Range | None = Field(
        None, description="lower clip of the dispersed range [m] (default: half of range_m)"
    )
    lateral_dispersion_m: NonNegRange = 0.5
    velocity_dispersion_m_s: NonNegSpeed = 0.005
    closing_speed_m_s: NonNegSpeed = 0.0


class EnvConfig(StrictModel):
    """Gymnasium environment settings."""

    perception: Literal["tridar", "truth", "truth+noise"] = "tridar"
    frame_period_s: FramePeriod = 0.2
    frame_skip: Annotated[Int, Field(ge=1, le=1000)] = 1
    max_episode_steps: Annotated[Int, Field(ge=1, le=MAX_COUNT)] = 2000
    max_range_m: Range = 100.0
    corridor_half_angle_deg: Annotated[Float, Field(gt=0, le=180)] | None = None
    truth_noise_position_m: Sigma = 0.01
    truth_noise_velocity_m_s: NonNegSpeed = 0.002
    truth_noise_attitude_deg: Annotated[Float, Field(ge=0, le=180)] = 0.5
    truth_noise_rate_deg_s: Rate = 0.05
    truth_noise_correlation_s: NonNegPeriod = Field(
        0.0, description="time constant of the truth+noise errors (first-order Gauss-Markov; 0: "
        "independent each step). The pipeline's errors persist for seconds, not one frame"
    )
    truth_noise_reference: Literal["port", "center_of_mass"] = Field(
        "port", description="point of the target where the truth+noise position error is applied: "
        "the docking port (as the pipeline, which observes and filters about the port) or the "
        "centre of mass (then attitude errors also move the port by the lever arm)"
    )
    speed_limit_gain_s: Annotated[Float, Field(gt=0, le=100)] = Field(
        0.02, description="v_max = v0 + gain * range"
    )
    speed_limit_floor_m_s: Speed = 0.08
    speed_profile_gain_s: Annotated[Float, Field(ge=0, le=100)] = Field(
        0.01, description="reference closing speed v_ref = envelope mid-speed + gain * distance "
        "(reward.speed_profile)"
    )
    speed_profile_max_m_s: Speed = Field(0.2, description="cap of the reference closing speed")
    initial: InitialStateConfig = InitialStateConfig()
    envelope: DockingEnvelopeConfig = DockingEnvelopeConfig()
    reward: RewardConfig = RewardConfig()
    point_cloud_size: Annotated[Int, Field(ge=1, le=1_000_000)] = 1024


class MissionConfig(StrictModel):
    """A whole scenario: target, sensor, estimators, dynamics and environment."""

    name: str = Field("mission", max_length=200)
    description: str = Field("", max_length=10_000)
    target: TargetConfig = TargetConfig()
    sensor: SensorConfig = SensorConfig()
    flash: FlashLidarConfig = FlashLidarConfig()
    pipeline: PipelineConfig = PipelineConfig()
    dynamics: DynamicsConfig = DynamicsConfig()
    env: EnvConfig = EnvConfig()


# ---------------------------------------------------------------------------------------------
# Reading YAML: bounded in size, nesting and alias expansion whatever the file holds
# ---------------------------------------------------------------------------------------------
#: Largest config file read [bytes]; the shipped ones are a few kB.
MAX_FILE_BYTES = 1 << 20
#: Deepest nesting of mappings and sequences (a scalar counts as a level); configs use about 5.
MAX_NESTING = 32
#: Most values a document may hold with its aliases expanded (a billion-laughs file holds 10^9).
MAX_NODES = 20_000
#: Longest shown value or key in an error message [characters].
MAX_SHOWN = 80
#: Errors listed in one message; the rest are counted.
MAX_LISTED = 5

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxdict, _REPR.maxlist, _REPR.maxtuple, _REPR.maxset = 3, 4, 4, 4, 4
_REPR.maxstring, _REPR.maxlong, _REPR.maxother = MAX_SHOWN, 40, MAX_SHOWN


def short_repr(value: Any, limit: int = MAX_SHOWN) -> str:
    """``repr`` of a value cut to ``limit`` characters, in bounded time whatever its size.

    A billion-laughs structure, a huge int or a hostile ``__repr__`` never reaches ``repr``
    whole; the result is one line.
    """
    if isinstance(value, int) and value.bit_length() > 128:
        return f"<int of {int(value.bit_length() * math.log10(2)) + 1} digits>"
    try:
        text = _REPR.repr(value)
    except Exception:  # noqa: BLE001  (an int past str()'s digit limit, a failing __repr__)
        text = f"<{type(value).__name__}>"
    text = text.replace("\n", "\\n")
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _LimitError(yaml.MarkedYAMLError):
    """A document refused for its size, nesting or aliases (not a syntax error)."""


class _ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and bounds nesting and node count while it
    composes (PyYAML's composer recurses once per level: 20,000 levels were a RecursionError)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):  # the anchored node again: neither deeper nor new
            return super().compose_node(parent, index)
        self._nodes += 1
        self._depth += 1
        try:
            mark = self.peek_event().start_mark
            if self._depth > MAX_NESTING:
                raise _LimitError(problem=f"nested deeper than {MAX_NESTING} levels", problem_mark=mark)
            if self._nodes > MAX_NODES:
                raise _LimitError(problem=f"more than {MAX_NODES} values", problem_mark=mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


# YAML 1.1 (PyYAML) reads ``1e-3`` as a string, which a number field now refuses; YAML 1.2 and every
# reader of a config take it for the number it looks like.
_ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _check_duplicate_keys(loader: _ConfigLoader, node: yaml.MappingNode) -> None:
    first: dict[Any, yaml.Node] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
            continue  # merge keys may repeat keys on purpose; a non-scalar key PyYAML refuses itself
        key = loader.construct_object(key_node)
        if key in first:
            raise yaml.constructor.ConstructorError(
                problem=f"duplicate key {short_repr(key)} (first at line "
                f"{first[key].start_mark.line + 1})",
                problem_mark=key_node.start_mark,
            )
        first[key] = key_node


def _check_document(loader: _ConfigLoader, root: yaml.Node) -> None:
    """Refuse a composed document whose aliases expand past :data:`MAX_NODES` values or
    :data:`MAX_NESTING` levels, or refer to themselves; and duplicate keys. Iterative, and each
    node is visited once: the expanded sizes are added up, never built."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        k = id(node)
        if done:
            on_path.discard(k)
            kids = _children(node)
            size[k] = 1 + sum(size[id(c)] for c in kids)
            depth[k] = 1 + max((depth[id(c)] for c in kids), default=0)
            if size[k] > MAX_NODES:
                raise _LimitError(
                    problem=f"aliases expand to more than {MAX_NODES} values", problem_mark=node.start_mark
                )
            if depth[k] > MAX_NESTING:
                raise _LimitError(
                    problem=f"aliases nest deeper than {MAX_NESTING} levels", problem_mark=node.start_mark
                )
            continue
        if k in size:
            continue
        if k in on_path:
            raise _LimitError(problem="an alias refers to its own anchor", problem_mark=node.start_mark)
        on_path.add(k)
        if isinstance(node, yaml.MappingNode):
            _check_duplicate_keys(loader, node)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node))


def parse_yaml(text: str) -> Any:
    """One YAML document with the safe loader, refused (``yaml.YAMLError``) when it nests deeper
    than :data:`MAX_NESTING`, expands past :data:`MAX_NODES` values or repeats a key."""
    loader = _ConfigLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_document(loader, node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line: the problem and where (PyYAML's own message spans several lines)."""
    if isinstance(exc, yaml.MarkedYAMLError):
        what = " ".join(str(x) for x in (exc.context, exc.problem) if x)
        mark = exc.problem_mark or exc.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        return " ".join(what.split())[:200] + where
    return " ".join(str(exc).split())[:200]


def _read_text(p: Path) -> str:
    """The UTF-8 text of a regular file of at most :data:`MAX_FILE_BYTES` (read no further)."""
    try:
        st = p.stat()
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except (OSError, ValueError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise ConfigError(f"config file {p} cannot be read: {why}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"config file {p} is a directory; expected a YAML file")
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"config file {p} is not a regular file (a device or a pipe); expected a YAML file")
    too_big = f"config file {p} is larger than {MAX_FILE_BYTES} bytes; expected a config of a few kB"
    if st.st_size > MAX_FILE_BYTES:
        raise ConfigError(too_big)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror or exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(too_big)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"config file {p} is not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start}"
        ) from None


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping with the safe loader; an empty file is an empty mapping.

    Raises:
        ConfigError: a missing file, a directory, a file over :data:`MAX_FILE_BYTES`, bytes that
            are not UTF-8, invalid YAML (duplicate keys included), nesting past
            :data:`MAX_NESTING`, aliases expanding past :data:`MAX_NODES` values, or a document
            that is not a mapping; the message is one line naming the file.
    """
    p = Path(path)
    text = _read_text(p)
    try:
        data = parse_yaml(text)
    except _LimitError as exc:
        raise ConfigError(
            f"config file {p} is refused: {_yaml_problem(exc)}; expected a plain config"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {p} is not valid YAML: {_yaml_problem(exc)}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:
        # a constructor's own error: an int past str()'s digit limit, a timestamp's month 13
        raise ConfigError(
            f"config file {p} holds a value that cannot be read: {short_repr(str(exc), 200)}"
        ) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} holds a {type(data).__name__}; expected a mapping")
    return data


# ---------------------------------------------------------------------------------------------
# Overrides, validation and saving
# ---------------------------------------------------------------------------------------------
M = TypeVar("M", bound=BaseModel)


def _expected(msg: str) -> str:
    for prefix in ("Input should be ", "Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
            break
    msg = " ".join(msg.split())
    return (msg[:1].lower() + msg[1:])[:200]


def _loc(loc: tuple[Any, ...]) -> str:
    return ".".join(p if isinstance(p, str) and p.isprintable() and len(p) <= 40 else short_repr(p, 40)
                    for p in loc) or "<root>"


def _format_errors(exc: ValidationError, source: str) -> str:
    """One line: each error's field, its value (cut short) and what was expected."""
    errors = exc.errors()
    items = []
    for err in errors[:MAX_LISTED]:
        loc, value = _loc(err["loc"]), short_repr(err.get("input"))
        if err["type"] == "extra_forbidden":
            items.append(f"{loc}: unknown key (value {value}); check the spelling")
        elif err["type"] == "missing":
            items.append(f"{loc}: missing; expected a value (the field is required)")
        else:
            items.append(f"{loc}: got {value}, expected {_expected(err['msg'])}")
    if len(errors) > MAX_LISTED:
        items.append(f"and {len(errors) - MAX_LISTED} more")
    return f"invalid configuration in {source}: " + "; ".join(items)


def _check_override_values(overrides: dict[Any, Any]) -> None:
    """Refuse overrides nested deeper than :data:`MAX_NESTING` or holding more than
    :data:`MAX_NODES` values (a list that contains itself never ends); iterative."""
    count = 0
    stack: list[tuple[Any, int, str]] = [(overrides, 1, "")]
    while stack:
        value, level, key = stack.pop()
        count += 1
        if level > MAX_NESTING:
            raise ConfigError(
                f"override {key} is nested deeper than {MAX_NESTING} levels; expected a plain value"
            )
        if isinstance(value, (dict, list, tuple, set, frozenset)):
            if count + len(value) > MAX_NODES:
                raise ConfigError(f"overrides hold more than {MAX_NODES} values; expected a few settings")
            if isinstance(value, dict):
                stack.extend((v, level + 1, key or _loc((k,))) for k, v in value.items())
            else:
                stack.extend((v, level + 1, key) for v in value)


def _split_key(key: Any) -> list[str]:
    if not isinstance(key, str):
        raise ConfigError(f"override key {short_repr(key)} is a {type(key).__name__}; expected a string "
                          "such as 'env__frame_skip'")
    parts = key.replace(".", "__").split("__")
    if not all(parts):
        raise ConfigError(f"override key {short_repr(key)} has an empty name; expected names joined by "
                          "'__' or '.' such as 'env__frame_skip'")
    return parts


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Merge overrides into a nested mapping. Keys nest with ``__`` or ``.`` (``sensor__tof__bias_m``);
    a mapping value is merged recursively.

    Raises:
        ConfigError: a key that is not a string or has an empty name; a key that goes through a
            value that is not a section (``{"env": 3, "env__frame_skip": 2}`` would otherwise
            drop the whole ``env`` section), or through a section an earlier override set to
            null; values nested past :data:`MAX_NESTING` or holding more than :data:`MAX_NODES`.
    """
    _check_override_values(overrides)
    out = _deep_copy(data)
    nulled: set[tuple[str, ...]] = set()  # sections an override of this call set to None
    for key, value in overrides.items():
        parts = _split_key(key)
        node = out
        for i, part in enumerate(parts[:-1]):
            path = tuple(parts[: i + 1])
            nxt = node.get(part)
            if nxt is None and path not in nulled:  # an absent (or null) section starts empty
                nxt = node[part] = {}
            elif not isinstance(nxt, dict):
                raise ConfigError(
                    f"override {key}: {'.'.join(path)} is {short_repr(nxt)}, not a section; "
                    f"expected a mapping to set {parts[-1]} in"
                )
            node = nxt
        leaf = parts[-1]
        current = node.get(leaf)
        if isinstance(value, dict) and isinstance(current, dict):
            node[leaf] = apply_overrides(current, value)
        else:
            if value is None and isinstance(current, dict):
                nulled.add(tuple(parts))
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
    try:
        exists = p.exists()
    except (OSError, ValueError):  # a name too long for the file system: load_yaml says why
        exists = False
    if not p.suffix and not exists:
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
        ConfigError: a missing or unreadable file (see :func:`load_yaml`), bad overrides (see
            :func:`apply_overrides`), unknown keys, or values of the wrong type or out of range;
            the message is one line naming each field, its value and what was expected.
    """
    return resolve_config(path, overrides, model)


def resolve_config(
    path: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    model: type[M] = MissionConfig,  # type: ignore[assignment]
) -> M:
    """:func:`load_config` with the overrides as a mapping (a user's dict: a key that is not a
    string, or one named ``path`` or ``model``, is an override like any other, refused or applied,
    never a Python ``TypeError``)."""
    data: dict[str, Any] = {}
    source = "defaults"
    if path is not None:
        if not isinstance(path, (str, os.PathLike)):
            raise ConfigError(
                f"config={short_repr(path)} ({type(path).__name__}); expected a YAML path or a mission name"
            )
        p = config_path(path)
        data = load_yaml(p)
        source = f"config file {p}"
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            f"overrides={short_repr(overrides)} ({type(overrides).__name__}); expected a mapping"
        )
    if overrides:
        data = apply_overrides(data, overrides)
        source += f" (with overrides {short_repr(sorted(map(str, overrides)))})"
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
