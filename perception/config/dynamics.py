"""Configuration of the relative dynamics: the reference orbit, the target's attitude motion and
the chaser (mass, propulsion, attitude mode, mounted frames, inertial sensors)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StrictBool

from perception.config.types import (
    MAX_ACCEL_M_S2,
    MAX_ALTITUDE_M,
    MAX_ISP_S,
    MAX_MASS_KG,
    MAX_SIZE_M,
    Angles3,
    Float,
    Force,
    NonNegMass,
    Rate,
    StrictModel,
    Vec3,
)


class OrbitConfig(StrictModel):
    """The target's circular reference orbit."""

    altitude_m: Annotated[Float, Field(gt=0, le=MAX_ALTITUDE_M)] = 400_000.0
    inclination_deg: Annotated[Float, Field(ge=0, le=180)] = 51.6
    model: Literal["cw", "nonlinear"] = "cw"
    j2: StrictBool = False
    sun_beta_deg: Annotated[Float, Field(ge=-90, le=90)] = Field(
        0.0, description="angle of the Sun above the orbit plane [deg] (toward +z LVLH)"
    )
    sun_phase_deg: Annotated[Float, Field(ge=-360, le=360)] = Field(
        0.0, description="the Sun's in-plane direction at t = 0, from the radial (+x LVLH) toward "
        "+V-bar (+y) [deg]: 0 is local noon, 180 midnight (in eclipse)"
    )


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
    attitude: Literal["ideal", "pointing", "controlled"] = Field(
        "ideal", description="ideal: the docking frame held parallel to the port frame; pointing: "
        "the body +z aimed at the target's centre of mass, body +x along orbit normal x +z (ideal "
        "attitude control, for a fly-around); controlled: torques from the action"
    )
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

