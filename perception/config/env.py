"""Configuration of the Gymnasium environment: perception mode, timing, limits, truth noise, the
initial state, the docking envelope and the reward weights."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

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

