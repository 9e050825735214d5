"""Where the agent's state vector comes from: the TriDAR pipeline or a truth stand-in.

``perception="tridar"`` runs the full pipeline (sensor -> modes -> estimators -> filter) on the
truth scene; ``"truth"`` hands over the exact relative state (for ablations and fast training) and
``"truth+noise"`` adds Gaussian errors with the configured standard deviations. All three return
the same :class:`~perception.state.StateVector`, so policies and controllers cannot tell the
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
from perception.state import Mode, StateVector, Validity
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


@functools.lru_cache(maxsize=32)
def _truth_covariance(sigmas: tuple[float, float, float, float]) -> np.ndarray:
    """(12, 12) diagonal covariance of a truth(-plus-noise) state; shared, read-only."""
    var = np.repeat(np.square(np.maximum(np.array(sigmas, dtype=np.float64), 1e-6)), 3)
    cov = np.diag(var)
    cov.setflags(write=False)
    return cov


def state_from_truth(
    t: float,
    truth: SensorTruth,
    sigmas: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    rng: np.random.Generator | None = None,
) -> StateVector:
    """A tracking-mode state built from truth, optionally with Gaussian errors.

    Args:
        t: time [s].
        truth: true relative kinematics in the sensor frame.
        sigmas: 1-sigma errors (position [m], velocity [m/s], attitude [rad], rate [rad/s]).
        rng: generator for the errors (required when any sigma > 0).
    """
    p = truth.T_sensor_target[:3, 3].copy()
    v = truth.velocity.copy()
    R = truth.T_sensor_target[:3, :3]
    w = truth.angular_velocity.copy()
    sigmas = tuple(float(s) for s in sigmas)
    sp, sv, sa, sw = sigmas
    if sp > 0 or sv > 0 or sa > 0 or sw > 0:
        if rng is None:
            raise ValueError("rng=None; a Generator is needed when noise sigmas are > 0")
        e = rng.standard_normal(12)
        p = p + sp * e[0:3]
        v = v + sv * e[3:6]
        R = Rotation.from_rotvec(sa * e[6:9]).as_matrix() @ R
        w = w + sw * e[9:12]
    rng_m = math.sqrt(float(p @ p))
    return StateVector(
        t=t,
        mode=Mode.TRACKING,
        valid=_ALL_VALID,
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
    """The exact relative state (``perception="truth"``) or truth plus noise (``"truth+noise"``)."""

    def __init__(self, cfg: MissionConfig, noisy: bool) -> None:
        e = cfg.env
        self.sigmas = (
            (e.truth_noise_position_m, e.truth_noise_velocity_m_s,
             float(np.deg2rad(e.truth_noise_attitude_deg)), float(np.deg2rad(e.truth_noise_rate_deg_s)))
            if noisy else (0.0, 0.0, 0.0, 0.0)
        )
        self.last_cloud = None

    def reset(self, rng: np.random.Generator) -> None:
        del rng

    def observe(self, world: World, rng: np.random.Generator) -> StateVector:
        return state_from_truth(world.t, world.sensor_truth(), self.sigmas, rng)


class TriDARObserver:
    """The full TriDAR pipeline (:class:`perception.pipeline.TriDAR`) on the truth scene."""

    def __init__(self, cfg: MissionConfig, target: TargetModel) -> None:
        from perception.pipeline import TriDAR  # the product's perception, built on first use

        self.pipeline = TriDAR(cfg, target)

    @property
    def last_cloud(self) -> object | None:
        return getattr(self.pipeline, "last_cloud", None)

    def reset(self, rng: np.random.Generator) -> None:
        self.pipeline.reset(rng)  # start-up state; the prepared model and PAH database are kept

    def observe(self, world: World, rng: np.random.Generator) -> StateVector:
        del rng  # the pipeline owns the generator handed to reset()
        return self.pipeline.step(world.scene(), world.t)


def make_observer(cfg: MissionConfig, target: TargetModel) -> Observer:
    """Factory for ``cfg.env.perception``."""
    kind = cfg.env.perception
    if kind == "truth":
        return TruthObserver(cfg, noisy=False)
    if kind == "truth+noise":
        return TruthObserver(cfg, noisy=True)
    return TriDARObserver(cfg, target)
