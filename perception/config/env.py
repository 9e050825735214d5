"""Configuration of the Gymnasium environment: perception mode, timing, limits, truth noise, the
initial state, the docking envelope and the reward weights."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StrictBool, model_validator

from perception.config.types import (
    MAX_COUNT,
    MAX_RATE_DEG_S,
    Float,
    FramePeriod,
    Int,
    NonNegPeriod,
    NonNegRange,
    NonNegSpeed,
    Range,
    Rate,
    Sigma,
    Size,
    Speed,
    StrictModel,
    Weight,
)


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
    aim_sensor: StrictBool = Field(
        True, description="with controlled attitude (dynamics.chaser.attitude: controlled), the "
        "chaser starts turned so that its sensor's boresight points at the target's centre of "
        "mass (the hand-over from far-range navigation), then the 1-deg attitude error; False "
        "starts it aligned with the port axis, which puts a target more than ~15 deg off the "
        "axis outside the TriDAR's field of view"
    )
    pose_known: StrictBool = Field(
        False, description="the pipeline starts from the true relative pose at reset (undocking: "
        "the mated pose is known), as an external seed for its first acquisition"
    )


class DecisionScheduleConfig(StrictModel):
    """Decision intervals that lengthen with range, so a long approach stays a few thousand steps.

    A step holds the action over ``frame_skip + floor((range - start_m) / step_m)`` frames (at
    most ``max_frames``), where ``range`` is the range of the state vector the agent just saw
    (:func:`tridar_env.schedule.decision_frames`; the last valid one while none is valid), so an agent
    knows each step's length from its own observation. The sensor takes one frame per step.
    """

    start_m: NonNegRange = Field(300.0, description="range [m] inside which a step is frame_skip frames")
    step_m: Range = Field(50.0, description="one more frame per step for every this many metres beyond start_m")
    max_frames: Annotated[Int, Field(ge=1, le=1000)] = 60


class FlyAroundConfig(StrictModel):
    """The fly-around task (``env.task: fly_around``): undock, back out to the standoff, circle the
    target in the orbital plane and come back to the port axis.

    The swept angle is the chaser's turn about the target's centre of mass in the orbital plane
    (unwrapped, counted in the direction of ``direction``); the task is complete once it reaches
    ``sweep_deg`` with the chaser inside the standoff band. Inside ``keep_out_radius_m`` of the
    centre of mass the episode ends (``keep_out``).
    """

    standoff_m: Range = Field(100.0, description="radius of the fly-around about the centre of mass [m]")
    band_m: Size = Field(15.0, description="tolerated distance from the standoff radius [m]")
    keep_out_radius_m: Range = Field(
        40.0, description="keep-out sphere about the centre of mass [m] (entered only from the port "
        "axis while undocking, within keep_out_axis_deg of it)"
    )
    keep_out_axis_deg: Annotated[Float, Field(gt=0, le=90)] = Field(
        15.0, description="half-angle of the departure cone about the port axis inside the keep-out sphere"
    )
    sweep_deg: Annotated[Float, Field(gt=0, le=1080)] = 360.0
    direction: Literal[1, -1] = Field(
        1, description="+1: counter-clockwise about the orbit normal (+z LVLH), -1: clockwise"
    )


class FlyAroundRewardConfig(StrictModel):
    """Weights of the fly-around reward terms (``info["reward_<name>"]``): ``sweep`` per radian of
    swept angle (potential-based), ``band`` per second per metre outside the standoff band,
    ``time`` per second, ``fuel`` per kg, ``success`` on completion, ``keep_out`` on entering the
    keep-out sphere, ``exit`` on leaving the bounds."""

    sweep: Weight = 10.0
    band: Weight = 0.01
    time: Weight = 0.002
    fuel: Weight = 10.0
    success: Weight = 100.0
    keep_out: Weight = 100.0
    exit: Weight = 50.0


class EnvConfig(StrictModel):
    """Gymnasium environment settings."""

    perception: Literal["tridar", "flash", "truth", "truth+noise"] = Field(
        "tridar", description="tridar: the scanning TriDAR pipeline; flash: the same modes, filter "
        "and integrity on seed 003's flash LiDAR (mission section flash); truth, truth+noise: "
        "stand-ins"
    )
    task: Literal["docking", "fly_around"] = Field(
        "docking", description="docking: reach the port inside the capture envelope; fly_around: "
        "undock and circle the target (env.fly_around)"
    )
    frame_period_s: FramePeriod = 0.2
    frame_skip: Annotated[Int, Field(ge=1, le=1000)] = Field(
        1, description="frames per agent step (the action is held over them); the pipeline "
        "(tridar, flash) still processes every frame"
    )
    decision_schedule: DecisionScheduleConfig | None = Field(
        None, description="decision intervals that lengthen with range (None: frame_skip frames)"
    )
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
    fly_around: FlyAroundConfig = FlyAroundConfig()
    fly_around_reward: FlyAroundRewardConfig = FlyAroundRewardConfig()

    @model_validator(mode="after")
    def _fly_around(self) -> EnvConfig:
        fa = self.fly_around
        if self.task == "fly_around" and fa.standoff_m - fa.band_m <= fa.keep_out_radius_m:
            raise ValueError(
                f"fly_around.standoff_m={fa.standoff_m} - band_m={fa.band_m} must stay outside "
                f"keep_out_radius_m={fa.keep_out_radius_m}"
            )
        return self

