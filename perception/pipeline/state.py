"""What a TriDAR publishes: the ``StateVector``, its operating ``Mode`` and field ``Validity``.

Quantities are relative and kinematic, as the sensor observes them:

* ``position`` [m]: the target body origin (its centre of mass) in the sensor frame;
* ``velocity`` [m/s]: the time derivative of ``position`` in sensor coordinates;
* ``quaternion``: scalar-first ``q_sensor_target`` (target body -> sensor), ``w >= 0``;
* ``angular_velocity`` [rad/s]: the target's angular velocity relative to the sensor frame,
  in sensor coordinates;
* ``range`` [m] and ``range_rate`` [m/s] (negative when closing) to the target, and ``bearing``
  ``(az, el)`` [rad] of the line of sight (az toward +x, el toward -y, i.e. up).

Every pose carries a ``protection_level`` [m], a bound on the docking port's position error at the
mission's integrity risk (:mod:`perception.pipeline.integrity`), and the ``alert_limit`` [m] it is held to.
A pose whose protection level exceeds its alert limit is published with ``valid.degraded`` set:
its numbers are the best estimate there is, but it is not valid for closing in (``valid.pose`` is
False). Without a pose both are 0.

Fields that a mode cannot measure are flagged in ``valid`` and hold zeros: never stale or made-up
numbers, and never NaN. ``covariance`` is ``(12, 12)`` over ``[position, velocity, attitude
(small-angle rotation vector, sensor frame), angular_velocity]``; the blocks of invalid fields hold
a large variance (``INVALID_VARIANCE``). It is the accuracy covariance (what the error typically
is: its NEES is about 3, ``integrity.accuracy_bias_*``); the protection level is computed from the
integrity covariance, which adds the larger correlated-error allowance of the worst shapes
(``integrity.bias_*``), so it always bounds at least what the covariance says.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields
from enum import IntEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Variance given to fields that are not measured (finite, so nothing downstream meets inf/NaN).
INVALID_VARIANCE = 1e6

__all__ = ["Mode", "Validity", "StateVector", "TruthScene", "INVALID_VARIANCE"]


class Mode(IntEnum):
    """TriDAR high-level operating states (seed 000 section 3.3, Fig. 4)."""

    BEARING = 0
    SEARCH = 1
    TRACKING = 2


@dataclass(frozen=True)
class Validity:
    """Which fields of a :class:`StateVector` carry a measurement, and whether the pose meets its
    alert limit (``degraded``: it does not; see the module docstring)."""

    bearing: bool = False
    range: bool = False
    range_rate: bool = False
    position: bool = False
    velocity: bool = False
    attitude: bool = False
    angular_velocity: bool = False
    degraded: bool = False

    @classmethod
    def all(cls) -> Validity:
        """Every field measured, the pose within its alert limit."""
        return cls(*(True,) * (len(fields(cls)) - 1))

    @classmethod
    def bearing_only(cls) -> Validity:
        return cls(bearing=True, range=True, range_rate=True)

    def as_array(self) -> npt.NDArray[np.float32]:
        """(8,) float32 flags in field order, for observations."""
        return np.array([getattr(self, f.name) for f in fields(self)], dtype=np.float32)

    @property
    def pose(self) -> bool:
        """A pose to fly on: position and attitude measured and within the alert limit."""
        return self.position and self.attitude and not self.degraded


def _zeros(n: int) -> FloatArray:
    return np.zeros(n)


@dataclass
class StateVector:
    """One TriDAR output (see the module docstring for frames and units).

    Attributes:
        t: time the state applies to [s].
        mode: operating mode that produced it.
        valid: which fields hold measurements.
        position: (3,) [m], sensor frame.
        velocity: (3,) [m/s], sensor frame.
        quaternion: (4,) scalar-first ``q_sensor_target``.
        angular_velocity: (3,) [rad/s], relative to the sensor, sensor frame.
        range: [m].
        range_rate: [m/s], negative when closing.
        bearing: (2,) azimuth and elevation [rad].
        covariance: (12, 12) over position, velocity, attitude, angular velocity.
        fitness: inlier fraction of the last registration (0 when none).
        n_points: points in the frame that produced it.
        latency: [s] between the end of the scan and the state becoming available.
        protection_level: [m] bound on the port position error at the integrity risk (0: no pose).
        alert_limit: [m] the error tolerated at this range (0: no pose).
        bearing_source: what measured ``bearing`` in bearing and search modes: ``"lidar"`` (the
            centroid of the returns), ``"thermal"`` (the thermal imager, beyond the LIDAR's
            reach) or ``""`` (no bearing, or one from the pose).
    """

    t: float
    mode: Mode
    valid: Validity
    position: FloatArray = field(default_factory=lambda: _zeros(3))
    velocity: FloatArray = field(default_factory=lambda: _zeros(3))
    quaternion: FloatArray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    angular_velocity: FloatArray = field(default_factory=lambda: _zeros(3))
    range: float = 0.0
    range_rate: float = 0.0
    bearing: FloatArray = field(default_factory=lambda: _zeros(2))
    covariance: FloatArray = field(default_factory=lambda: np.eye(12) * INVALID_VARIANCE)
    fitness: float = 0.0
    n_points: int = 0
    latency: float = 0.0
    protection_level: float = 0.0
    alert_limit: float = 0.0
    bearing_source: str = ""

    def __post_init__(self) -> None:
        for name, n in (("position", 3), ("velocity", 3), ("quaternion", 4),
                        ("angular_velocity", 3), ("bearing", 2)):
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if arr.shape != (n,):
                raise ValueError(f"StateVector.{name} has shape {arr.shape}; expected ({n},)")
            setattr(self, name, arr)
        self.covariance = np.asarray(self.covariance, dtype=np.float64)
        if self.covariance.shape != (12, 12):
            raise ValueError(f"StateVector.covariance has shape {self.covariance.shape}; expected (12, 12)")
        if not self.is_finite():
            raise ValueError("StateVector holds non-finite values; invalid fields must be zeros")

    def is_finite(self) -> bool:
        """True when every number in the state is finite."""
        # One concatenation and one reduction: this runs on every env step.
        values = np.concatenate((
            (self.t, self.range, self.range_rate, self.fitness, self.latency,
             self.protection_level, self.alert_limit),
            self.position, self.velocity, self.quaternion, self.angular_velocity, self.bearing,
            self.covariance.reshape(-1),
        ))
        return bool(np.isfinite(values).all())

    @property
    def T_sensor_target(self) -> FloatArray:
        """(4, 4) pose of the target in the sensor frame (identity rotation when invalid)."""
        from perception.geometry import T_from_quat_pos

        return T_from_quat_pos(self.quaternion, self.position)

    @classmethod
    def invalid(cls, t: float, mode: Mode = Mode.BEARING) -> StateVector:
        """A state with nothing measured (start-up, blackout before any return)."""
        return cls(t=t, mode=mode, valid=Validity())


@dataclass(frozen=True)
class TruthScene:
    """What the world hands the sensor for one frame (truth; perception code only scans it).

    Attributes:
        T_sensor_target: (4, 4) pose at the frame start time ``t``.
        t: frame start time [s].
        motion: relative motion over the frame (motion during the scan): a
            ``perception.sensing.sensors.RelativeMotion`` or a callable ``t -> (4, 4) T_sensor_target``.
        sun_direction_target: (3,) unit vector from the target toward the Sun, target body frame,
            or None when the target is in the Earth's shadow (what the thermal imager needs).
    """

    T_sensor_target: FloatArray
    t: float
    motion: Callable[[float], FloatArray] | object | None = None
    sun_direction_target: FloatArray | None = None
