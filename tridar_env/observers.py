"""Where the agent's state vector comes from: the TriDAR pipeline or a truth stand-in.

``perception="tridar"`` runs the full pipeline (sensor -> modes -> estimators -> filter) on the
truth scene; ``"truth"`` hands over the exact relative state (for ablations and fast training) and
``"truth+noise"`` adds Gaussian errors with the configured standard deviations (optionally
correlated in time and applied about the docking port). All three return
the same :class:`~perception.pipeline.state.StateVector`, so policies and controllers cannot tell the
plumbing apart, only the quality.
"""

from __future__ import annotations

import functools
import math
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from perception.config import MissionConfig
from perception.geometry import fast_matrix_to_quat
from perception.pipeline.integrity import (
    alert_limit,
    integrity_factor,
    port_covariance,
    protection_level,
)
from perception.pipeline.state import Mode, StateVector, Validity
from perception.targets import TargetModel
from tridar_env.world import SensorTruth, World


class Observer(Protocol):
    """Produces one :class:`StateVector` per frame."""

    def reset(self, rng: np.random.Generator) -> None: ...

    def observe(self, world: World, rng: np.random.Generator) -> StateVector: ...

    @property
    def last_cloud(self) -> object | None: ...


def bearing_of(p: np.ndarray) -> np.ndarray:
    """(az, el) [rad] of a sensor-frame vector: az toward +x, el toward -y (up)."""
    x, y, z = np.asarray(p, dtype=np.float64).reshape(3).tolist()
    return np.array([math.atan2(x, z), math.atan2(-y, math.hypot(x, z))])


_ALL_VALID = Validity.all()
_DEGRADED = Validity(*(True,) * 8)


@functools.lru_cache(maxsize=32)
def _truth_covariance(sigmas: tuple[float, float, float, float]) -> np.ndarray:
    """(12, 12) diagonal covariance of a truth(-plus-noise) state; shared, read-only."""
    var = np.repeat(np.square(np.maximum(np.array(sigmas, dtype=np.float64), 1e-6)), 3)
    cov = np.diag(var)
    cov.setflags(write=False)
    return cov


def truth_protection_level(
    sigmas: tuple[float, float, float, float], R_sensor_target: np.ndarray, r_port: np.ndarray | None,
    ref_point: np.ndarray | None, risk: float,
) -> float:
    """Protection level [m] of a truth(-plus-noise) state: the port error bound of its errors.

    With the errors applied at the port (``ref_point`` = the port) the port moves by the position
    error alone; otherwise the attitude error swings the port about the centre of mass too.
    """
    k = integrity_factor(risk)
    sp = max(sigmas[0], 1e-6)
    if r_port is None or (ref_point is not None and np.array_equal(ref_point, r_port)):
        return k * sp
    return protection_level(port_covariance(_truth_covariance(sigmas), R_sensor_target, r_port), k)


def state_from_truth(
    t: float,
    truth: SensorTruth,
    sigmas: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    rng: np.random.Generator | None = None,
    *,
    errors: np.ndarray | None = None,
    ref_point: np.ndarray | None = None,
    port: np.ndarray | None = None,
    integrity: tuple[float, float, float] | None = None,
) -> StateVector:
    """A tracking-mode state built from truth, optionally with Gaussian errors.

    Args:
        t: time [s].
        truth: true relative kinematics in the sensor frame.
        sigmas: 1-sigma errors (position [m], velocity [m/s], attitude [rad], rate [rad/s]).
        rng: generator for the errors (required when any sigma > 0 and ``errors`` is None).
        errors: ``(12,)`` unit-variance error draws (position, velocity, rotation vector, rate),
            e.g. a correlated sequence; drawn from ``rng`` when None.
        ref_point: target-frame point where the position error applies (the attitude error
            turns the target about it); None: the target origin (centre of mass).
        port: (3,) port position in the target frame [m] (for the protection level).
        integrity: ``(risk, alert_limit_m, alert_limit_range_m)`` (``pipeline.integrity``);
            None: no protection level (0) and never degraded.
    """
    p = truth.T_sensor_target[:3, 3].copy()
    v = truth.velocity.copy()
    R = truth.T_sensor_target[:3, :3]
    w = truth.angular_velocity.copy()
    sigmas = tuple(float(s) for s in sigmas)
    sp, sv, sa, sw = sigmas
    if sp > 0 or sv > 0 or sa > 0 or sw > 0:
        if errors is None:
            if rng is None:
                raise ValueError("rng=None; a Generator is needed when noise sigmas are > 0")
            errors = rng.standard_normal(12)
        e = errors
        R_est = Rotation.from_rotvec(sa * e[6:9]).as_matrix() @ R
        if ref_point is None:
            p = p + sp * e[0:3]
        else:
            # The reference point moves by the position error only; the rest of the target
            # turns about it with the attitude error.
            p = p + R @ ref_point + sp * e[0:3] - R_est @ ref_point
        R = R_est
        v = v + sv * e[3:6]
        w = w + sw * e[9:12]
    rng_m = math.sqrt(float(p @ p))
    pl = al = 0.0
    valid = _ALL_VALID
    if integrity is not None:
        risk, al_m, al_range = integrity
        pl = truth_protection_level(sigmas, R, port, ref_point, risk)
        port_s = p if port is None else p + R @ port
        al = alert_limit(math.sqrt(float(port_s @ port_s)), al_m, al_range)
        if pl > al:
            valid = _DEGRADED
    return StateVector(
        t=t,
        mode=Mode.TRACKING,
        valid=valid,
        protection_level=pl,
        alert_limit=al,
        position=p,
        velocity=v,
        quaternion=fast_matrix_to_quat(R),
        angular_velocity=w,
        range=rng_m,
        range_rate=float(p @ v) / max(rng_m, 1e-9),
        bearing=bearing_of(p),
        covariance=_truth_covariance(sigmas).copy(),
        fitness=1.0,
        n_points=0,
    )


class TruthObserver:
    """The exact relative state (``perception="truth"``) or truth plus noise (``"truth+noise"``).

    The noisy errors are first-order Gauss-Markov with time constant
    ``env.truth_noise_correlation_s`` (stationary 1-sigma = the configured sigmas; 0 gives
    independent errors each step), applied at ``env.truth_noise_reference`` (the docking port by
    default, like the pipeline's estimates, which are best where the sensor looks).
    """

    def __init__(self, cfg: MissionConfig, noisy: bool, target: TargetModel | None = None) -> None:
        e = cfg.env
        self.sigmas = (
            (e.truth_noise_position_m, e.truth_noise_velocity_m_s,
             float(np.deg2rad(e.truth_noise_attitude_deg)), float(np.deg2rad(e.truth_noise_rate_deg_s)))
            if noisy else (0.0, 0.0, 0.0, 0.0)
        )
        self.noisy = noisy and any(s > 0 for s in self.sigmas)
        self.tau = e.truth_noise_correlation_s
        self.ref_point = None
        self.port = None if target is None else np.array(target.T_target_port[:3, 3], dtype=np.float64)
        if e.truth_noise_reference == "port" and target is not None:
            self.ref_point = self.port
        ig = cfg.pipeline.integrity
        self.integrity = (ig.risk, ig.alert_limit_m, ig.alert_limit_range_m)
        self.last_cloud = None
        self._err: np.ndarray | None = None
        self._t_err = 0.0

    def reset(self, rng: np.random.Generator) -> None:
        del rng
        self._err = None

    def _errors(self, t: float, rng: np.random.Generator) -> np.ndarray:
        w = rng.standard_normal(12)
        if self._err is None or self.tau <= 0.0:
            self._err = w
        else:
            phi = math.exp(-max(t - self._t_err, 0.0) / self.tau)
            self._err = phi * self._err + math.sqrt(1.0 - phi * phi) * w
        self._t_err = t
        return self._err

    def observe(self, world: World, rng: np.random.Generator) -> StateVector:
        if not self.noisy:
            return state_from_truth(world.t, world.sensor_truth(), ref_point=self.ref_point, port=self.port,
                                    integrity=self.integrity)
        e = self._errors(world.t, rng)
        return state_from_truth(world.t, world.sensor_truth(), self.sigmas, errors=e,
                                ref_point=self.ref_point, port=self.port, integrity=self.integrity)


class TriDARObserver:
    """The full TriDAR pipeline (:class:`perception.pipeline.TriDAR`) on the truth scene, or with
    ``flash`` its flash-LiDAR form (:class:`perception.pipeline.flash.FlashPipeline`)."""

    def __init__(self, cfg: MissionConfig, target: TargetModel, flash: bool = False) -> None:
        # The product's perception, built on first use.
        if flash:
            from perception.pipeline.flash import FlashPipeline

            self.pipeline = FlashPipeline(cfg, target)
        else:
            from perception.pipeline import TriDAR

            self.pipeline = TriDAR(cfg, target)
        self.ego = cfg.pipeline.ego_motion

    @property
    def last_cloud(self) -> object | None:
        return getattr(self.pipeline, "last_cloud", None)

    def reset(self, rng: np.random.Generator) -> None:
        self.pipeline.reset(rng)  # start-up state; the prepared model and PAH database are kept
        # The first reset of a process builds the search's database, so no step stalls for it.
        self.pipeline.prepare()

    def observe(self, world: World, rng: np.random.Generator) -> StateVector:
        del rng  # the pipeline owns the generator handed to reset()
        return self.pipeline.step(world.scene(), world.t, ego=world.sensor_ego() if self.ego else None)


def make_observer(cfg: MissionConfig, target: TargetModel) -> Observer:
    """Factory for ``cfg.env.perception``."""
    kind = cfg.env.perception
    if kind == "truth":
        return TruthObserver(cfg, noisy=False, target=target)
    if kind == "truth+noise":
        return TruthObserver(cfg, noisy=True, target=target)
    return TriDARObserver(cfg, target, flash=kind == "flash")
