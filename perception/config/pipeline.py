"""Configuration of the TriDAR pipeline: modes and strategies by range, the approach corridor,
integrity (what a published pose promises) and the observability-aware scan plan."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StrictBool, model_validator

from perception.config.estimation import ICPConfig, PAHConfig
from perception.config.types import (
    MAX_ACCEL_M_S2,
    MAX_COUNT,
    MAX_FACTOR,
    MAX_RATE_DEG_S,
    Float,
    Int,
    Latency,
    NonNegFloat,
    NonNegPeriod,
    NonNegRange,
    Period,
    PositiveFloat,
    Range,
    Sigma,
    Size,
    StrictModel,
    UnitFloat,
)


class CorridorConfig(StrictModel):
    """Approach corridor: a cone about the port axis plus attitude and range bounds."""

    half_angle_deg: Annotated[Float, Field(gt=0, le=180)] = 15.0
    attitude_tolerance_deg: Annotated[Float, Field(gt=0, le=180)] = 20.0
    min_range_m: NonNegRange = 0.0
    max_range_m: Range = 1000.0
    max_rate_deg_s: Annotated[Float, Field(gt=0, le=1000)] | None = Field(
        None, description="a confirmed track whose target turns faster than this [deg/s] (its "
        "inertial rate with ego-motion, else the relative one) is outside the corridor: a "
        "target the mission holds in LVLH does not spin (None: no check)"
    )


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
    accuracy_bias_m: Sigma = Field(
        0.0005, description="1-sigma of the correlated position error at the port [m] that the "
        "published covariance carries on top of the filter's accuracy covariance (what the "
        "error typically is, NEES ~3); bias_m and bias_rad, sized for the worst shapes, go into "
        "the protection level only (the integrity covariance), as ARAIM keeps its accuracy and "
        "integrity covariances apart"
    )
    accuracy_bias_rad: Annotated[Float, Field(ge=0, le=1)] = Field(
        2.5e-5, description="the same growing with range [rad]: 1-sigma max(accuracy_bias_m, "
        "accuracy_bias_rad * range) (2.5 mm at 100 m; the fit to 40 m alone wanted none)"
    )
    accuracy_range_bias_m: Sigma = Field(
        0.001, description="1-sigma of the registrations' correlated error along the line of "
        "sight [m] on triangulated points that the published covariance carries (ICP's range "
        "offset on a shape, the same every frame: under 5 m within 1 mm on the library and the "
        "generated shapes once the filter models the tide; the +4 mm on the ISS-like port and "
        "-4 mm on hubble first fitted here were the filter's lag behind it); never more than "
        "the protection level's allowance there"
    )
    accuracy_tof_range_bias_m: Sigma = Field(
        0.001, description="the same on points the time of flight ranged [m], on top of its "
        "configured range bias (at 10-20 m the registrations sat +2.6 to +4.7 mm along the "
        "line of sight on ten shapes, the 5 mm bias included). Fitted with the others on ten "
        "shapes (library and generated, tuning seeds, the filter modelling the tide): position "
        "NEES 1.3-6.8 per shape (flat faces and hubble above 3); a static figure cannot fit "
        "every shape"
    )
    accuracy_calibration: StrictBool = Field(
        False, description="publish the correlated position error calibrated on the target's own "
        "model (TriDAR.accuracy_table, perception.pipeline.calibration: simulated tracking scans along "
        "the approach, across and along the line of sight by range, 10-25 s once per target and "
        "settings, cached on the target) in place of accuracy_range_bias_m and "
        "accuracy_tof_range_bias_m, over an accuracy_bias_m floor, each within the protection "
        "level's allowance; what check-target shows"
    )
    accuracy_scatter_window_frames: Annotated[Int, Field(ge=2, le=10_000)] | None = Field(
        50, description="the published covariance's registration noise is ICP's Cramer-Rao "
        "position covariance scaled by the mean square of the track's last this many "
        "registrations' whitened residuals to the filter (covariance matching, along and across "
        "the line of sight apart; PoseFilter.scatter_scale): on a generated assembly they "
        "scattered 2-2.5x their bound across it at 6-30 m, on others less. Changes only the "
        "published covariance (None: ICP's covariance as it is)"
    )
    bias_prediction_frames: Annotated[Int, Field(ge=1, le=10_000)] | None = Field(
        None, description="every this many settled tracking frames, the frame's scan pattern "
        "is taken again on the pipeline's model at the registered pose by the sensor without its "
        "noise and registered from there: where it lands off the pose is the registrations' "
        "bias (the beam footprint's first echo at edges; TrackingMode.predict_bias); the track's "
        "last 10 probes' mean goes into the published covariance at the port (one ray cast and "
        "one ICP per probe; only the published covariance). Off by default: on new seeds it "
        "took the worst overconfident shapes from NEES 6.4 / 6.0 / 5.7 to 2.8 / 4.7 / 4.9 but "
        "the conservative ones further down (iss_port 2.4 -> 1.3), the static figures already "
        "covering part of it (None: off)"
    )
    accuracy_lever_bias_m: Sigma = Field(
        0.0005, description="differential depth error across a scan [m] that tilts the "
        "registered pose: the published attitude carries this over the scan's lever arm (RMS "
        "distance of the frame's points from their centroid) as a turn about the port (a "
        "cubesat, 0.29 m lever, held a steady 0.15-0.2 deg at 5-35 m under a 0.07 deg sigma)"
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
    consistency_window_frames: Annotated[Int, Field(ge=2, le=1000)] | None = Field(
        None, description="consistency monitor: over the track's last this many registrations "
        "(the gate's accepted and rejected ones alike), the mean normalised innovation squared "
        "against the filter; beyond chi-square(6)'s 99.9 % band for that mean, the protection "
        "level grows by the square root of its ratio to 6 (a filter whose registrations keep "
        "disagreeing with it beyond both covariances does not know its error: a cylinder bus's "
        "new track at 33 m followed ICP's false roll basin 12 deg off, published valid 0.22 m off "
        "under a 0.19 m bound, while the right basin's registrations were rejected) (None: off)"
    )
    rival_votes: Annotated[Int, Field(ge=1, le=1000)] | None = Field(
        None, description="rival monitor (perception.pipeline.rivals): a sound registration the "
        "filter's gate rejects is a rival pose (the track's, moved onto it along the directions "
        "it observes) until this many accepted registrations have ruled it out beyond the gate; "
        "meanwhile the protection level grows by the port's offset to it (registrations that "
        "disagree with the track are evidence the track may be the wrong one: a PAH restart close "
        "in on hubble's aft face took a false basin 10 cm off in its plane and was published "
        "valid 9 cm off under a 5 cm bound between two rejections of the right basin) (None: off)"
    )
    ambiguity_margin: PositiveFloat = Field(
        0.05, description="a twin whose PAH score is within this of the tracked pose's, or "
        "better, makes the pose ambiguous"
    )
    slide_check_period_s: Period | None = Field(
        None, description="slide monitor (perception.pipeline.slides): every this many seconds of "
        "tracking (and on each new track's first frames), ICP from the pose pushed both ways along "
        "its least-constrained direction; what ICP does not bring back is added to the "
        "registrations' covariance along it (None: off)"
    )
    acquisition_floor_fraction: Annotated[Float, Field(ge=0, le=0.1)] = Field(
        0.0, description="a track PAH started from nothing takes its first pose with at least this "
        "fraction of the range as position sigma (PAH's basin, not ICP's noise: 0.3-0.8 m at 83 m "
        "on the ISS-like port); its velocity then comes from the frames that follow (0: off)"
    )
    min_valid_fitness: UnitFloat = Field(
        0.0, description="a frame whose registration explains less than this fraction of its "
        "points publishes its pose degraded, and a track lost after such frames is not "
        "continued (PAH starts over): on an exact model a sound pose explains nearly every "
        "return, and a track sliding along a truss's repeated bays fell to 0.6-0.9 while its "
        "filter still claimed decimetres (0: off)"
    )
    slide_hold_s: Annotated[Float, Field(ge=0, le=1e6)] = Field(
        0.0, description="a slide the monitor found stays on the registrations this long [s] "
        "after the last probe that found it, whatever the probes between say (0: until the next "
        "probe). Measured on FlyAround (seed 67) without slide_velocity_time_s: 30 s made it worse "
        "(4 valid-but-wrong runs in 100, 4 stalls), the filter's velocity along the weak axis "
        "going unchallenged; with the velocity floor, 10 s holds a flickering probe's slide "
        "(configs/missions/fly_around.yaml)"
    )
    slide_velocity_time_s: Annotated[Float, Field(gt=0, le=1e6)] | None = Field(
        None, description="while a slide of sigma s is on the registrations, the filter's "
        "velocity along it is kept uncertain by at least s / this [m/s]: the slide's error "
        "persists from frame to frame, and a filter that averaged it away became sure of a "
        "velocity the scans never observed (a fly-around track drifted 1-25 m along the ISS-like "
        "truss under a 0.7 m protection level) (None: off)"
    )
    slide_position_floor: bool = Field(
        False, description="while a slide of sigma s is held, the state a frame publishes is "
        "uncertain by at least s along it (a consider covariance; the filter's gain is left "
        "alone): the same slide's registrations share one offset, and after a filter restart on "
        "four of them, averaged as independent, a fly-around pose was 1.49 m off along the "
        "ISS-like truss under a 1.14 m protection level (its slide held at 2.78 m sigma) "
        "(False: off)"
    )
    slide_probe_fraction: Annotated[Float, Field(gt=0, le=0.1)] = Field(
        0.001, description="slide probe's push: max(3 sigma, this * range) [m]"
    )
    turn_check_period_s: Period | None = Field(
        None, description="turn monitor (perception.pipeline.slides): every this many seconds of "
        "tracking (and on each new track's first frames), ICP from the pose turned both ways by "
        "turn_probe_rad and to the best far turns (turn_grid_deg, turn_candidates) about its "
        "least-constrained rotation axis; "
        "a turned pose ICP does not bring back and that explains the scan about as well "
        "(ambiguity_margin) makes the turn uncertain by its offset, added to the registrations, "
        "held (slide_hold_s) and floored in the published attitude (slide_position_floor); a "
        "far turn that scores clearly better moves the track there. A generated cylinder bus whose roll only a thin boom pins (0-3 of "
        "~250 points) was published valid 180 deg off in roll, its off-axis port 0.83 m away "
        "under a 9 cm protection level (None: off)"
    )
    turn_probe_rad: Annotated[Float, Field(gt=0, le=0.5)] = Field(
        0.05, description="turn monitor's small push: max(3 sigma, this) [rad] (a flat valley)"
    )
    turn_grid_deg: Annotated[Float, Field(ge=1, le=90)] = Field(
        10.0, description="turn monitor's far turns: every this many degrees round the circle, "
        "scored as they stand (other basins: a rim's facets, a roll the model's near-symmetries "
        "miss)"
    )
    turn_candidates: Annotated[Int, Field(ge=1, le=36)] = Field(
        2, description="turn monitor: the best-scoring far turns polished by ICP and judged"
    )
    turn_far_every: Annotated[Int, Field(ge=1, le=1000)] = Field(
        5, description="turn monitor: far turns that the last probes all ruled out by a wide "
        "margin (10 ambiguity_margin), with no turn held, are looked at every this many probes"
    )
    turn_rule_out_probes: Annotated[Int, Field(ge=2, le=1000)] | None = Field(
        6, description="turn monitor: a far turn that explained the scan worse than the tracked "
        "pose at each of the last this many probes is ruled out, however small each lead (a "
        "sign test: a turn the scans cannot tell apart loses that many in a row with "
        "probability 2**-n); None: the mean lead alone decides"
    )

    @model_validator(mode="after")
    def _accuracy_within_integrity(self) -> IntegrityConfig:
        for acc, bound in (("accuracy_bias_m", "bias_m"), ("accuracy_bias_rad", "bias_rad"),
                           ("accuracy_lever_bias_m", "bias_m")):
            if getattr(self, acc) > getattr(self, bound):
                raise ValueError(
                    f"{acc}={getattr(self, acc)} exceeds {bound}={getattr(self, bound)}; the "
                    "protection level's allowance must cover the published covariance's"
                )
        return self


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


class CoarseRangeConfig(StrictModel):
    """A coarse range source beyond the LIDAR's reach (a radar or relative GPS, seed 000 section 1):
    range to the target's near surface along the line of sight to its centre, with Gaussian noise
    ``sqrt(sigma_m^2 + (sigma_fraction * range)^2)``, fused with the bearings in bearing mode."""

    enabled: StrictBool = False
    sigma_m: Sigma = 5.0
    sigma_fraction: Annotated[Float, Field(ge=0, le=1)] = 0.002
    max_range_m: Range = 100_000.0
    period_s: Period = Field(1.0, description="one range measurement per this many seconds at most")


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
    thermal_bearing: StrictBool = Field(
        False, description="bearing mode takes the thermal imager's bearing (mission ``thermal``) "
        "when the LIDAR has no returns (beyond its link budget): seed 000's tens of kilometres"
    )
    coarse_range: CoarseRangeConfig = CoarseRangeConfig()
    fine_only_tracking: StrictBool = Field(
        True, description="on an established track (rates estimated, the last frames accepted) "
        "ICP starts from the filter's prediction in its fine phase, without the coarse phase "
        "(one correspondence search fewer per frame)"
    )

