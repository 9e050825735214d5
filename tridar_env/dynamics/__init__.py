"""Truth dynamics: chaser relative orbital motion, target attitude and chaser mass.

Frames (see DESIGN.md and :mod:`.frames`): ECI; the target's LVLH / Hill frame (x radial away
from Earth, y along-track +V-bar, z orbit normal); the target body frame, whose attitude is
``R_lvlh_target`` at the API edge (scalar-first Hamilton quaternion ``(w, x, y, z)``, ``w >= 0``).
Relative states are ``(6,)`` ``[x, y, z, vx, vy, vz]`` of the chaser with respect to the target
in LVLH [m, m/s]; thrust accelerations are LVLH [m/s^2], held over a step (zero-order hold).

Modules, one job each (every public name is re-exported here):

* :mod:`.constants`: Earth's ``MU_EARTH``, ``R_EARTH``, ``J2_EARTH`` and standard gravity ``G0``.
* :mod:`.frames`: :func:`lvlh_frame`, :func:`relative_lvlh_from_eci`,
  :func:`eci_from_relative_lvlh` and the quaternion convention.
* :mod:`.orbit`: :func:`mean_motion`, :func:`cw_stm`, :func:`cw_acceleration`, :class:`CWPropagator` (Clohessy-Wiltshire,
  closed form), :func:`gravity_acceleration`, :func:`circular_orbit_state`,
  :class:`NonlinearRelativePropagator` (two-body + optional J2 integrated in ECI).
* :mod:`.attitude`: :func:`principal_axes`, :func:`spin_with_nutation`,
  :func:`rigid_body_rates`, :class:`RigidBodyAttitude` (torque-free rigid body) and
  :class:`TargetAttitudeModel` (``lvlh_hold``, ``inertial_hold``, ``tumble``).
* :mod:`.chaser`: :func:`mass_flow_rate`, :func:`propellant_used`, :func:`saturate_thrust`,
  :class:`ChaserMass` (propellant bookkeeping).
* ``_checks``: the argument checks they share.
"""

from tridar_env.dynamics.attitude import (
    RigidBodyAttitude,
    TargetAttitudeModel,
    principal_axes,
    rigid_body_rates,
    spin_with_nutation,
)
from tridar_env.dynamics.chaser import ChaserMass, mass_flow_rate, propellant_used, saturate_thrust
from tridar_env.dynamics.constants import G0, J2_EARTH, MU_EARTH, R_EARTH
from tridar_env.dynamics.frames import eci_from_relative_lvlh, lvlh_frame, relative_lvlh_from_eci
from tridar_env.dynamics.orbit import (
    CWPropagator,
    NonlinearRelativePropagator,
    circular_orbit_state,
    cw_acceleration,
    cw_stm,
    gravity_acceleration,
    mean_motion,
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
    "cw_acceleration",
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
