"""Truth dynamics: chaser relative orbital motion and target attitude (re-exported here)."""

from tridar_env.dynamics.orbit import (
    G0,
    J2_EARTH,
    MU_EARTH,
    R_EARTH,
    ChaserMass,
    CWPropagator,
    NonlinearRelativePropagator,
    RigidBodyAttitude,
    TargetAttitudeModel,
    circular_orbit_state,
    cw_stm,
    eci_from_relative_lvlh,
    gravity_acceleration,
    lvlh_frame,
    mass_flow_rate,
    mean_motion,
    principal_axes,
    propellant_used,
    relative_lvlh_from_eci,
    rigid_body_rates,
    saturate_thrust,
    spin_with_nutation,
)

__all__ = [
    "G0",
    "J2_EARTH",
    "MU_EARTH",
    "R_EARTH",
    "CWPropagator",
    "ChaserMass",
    "NonlinearRelativePropagator",
    "RigidBodyAttitude",
    "TargetAttitudeModel",
    "circular_orbit_state",
    "cw_stm",
    "eci_from_relative_lvlh",
    "gravity_acceleration",
    "lvlh_frame",
    "mass_flow_rate",
    "mean_motion",
    "principal_axes",
    "propellant_used",
    "relative_lvlh_from_eci",
    "rigid_body_rates",
    "saturate_thrust",
    "spin_with_nutation",
]

# doctest.testmod(tridar_env.dynamics) only looks at objects defined in this module; the
# re-exported ones are defined in the submodules, so name them here to run their examples.
__test__ = {name: globals()[name] for name in __all__ if callable(globals()[name])}
