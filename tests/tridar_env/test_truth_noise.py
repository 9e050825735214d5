"""The truth+noise stand-in: its errors follow the configured noise model (spread, reference
point, correlation time)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from perception.config import load_config
from perception.geometry import make_T, quat_to_matrix
from perception.targets import load_target
from tridar_env.observers import TruthObserver
from tridar_env.world import SensorTruth


@dataclass
class _StillWorld:
    """A fixed relative pose; only time moves."""

    truth: SensorTruth
    t: float = 0.0

    def sensor_truth(self) -> SensorTruth:
        return self.truth


def _errors(n: int, **env: float | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Port-position errors [m], centre-of-mass position errors [m], attitude errors [rad]."""
    cfg = load_config("final_approach", env__perception="truth+noise",
                      **{f"env__{k}": v for k, v in env.items()})
    target = load_target("iss_port")
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    T = make_T(R, np.array([0.3, -0.2, 20.0]))
    world = _StillWorld(SensorTruth(T, np.zeros(3), np.zeros(3)))
    obs = TruthObserver(cfg, noisy=True, target=target)
    rng = np.random.default_rng(5)
    obs.reset(rng)
    c = target.T_target_port[:3, 3]
    port, com, att = [], [], []
    for k in range(n):
        world.t = k * cfg.env.frame_period_s
        sv = obs.observe(world, rng)
        R_est = quat_to_matrix(sv.quaternion)
        port.append(sv.position + R_est @ c - (T[:3, 3] + R @ c))
        com.append(sv.position - T[:3, 3])
        att.append(math.acos(min(1.0, (np.trace(R.T @ R_est) - 1) / 2)))
    return np.array(port), np.array(com), np.array(att)


def test_white_errors_have_the_configured_spread_at_the_port() -> None:
    port, com, att = _errors(4000, truth_noise_position_m=0.02, truth_noise_attitude_deg=1.0)
    assert port.std(axis=0) == pytest.approx([0.02] * 3, rel=0.06)
    assert np.abs(port.mean(axis=0)).max() < 0.002
    # The attitude error turns the target about the port: the centre of mass, 11.7 m away,
    # moves by the lever arm (~0.2 m per degree), the port does not.
    assert np.sqrt(np.mean(np.sum(com**2, axis=1))) > 5 * np.sqrt(np.mean(np.sum(port**2, axis=1)))
    # Angle of a 3-D Gaussian rotation vector: RMS = sqrt(3) sigma.
    assert np.sqrt(np.mean(att**2)) == pytest.approx(math.sqrt(3) * math.radians(1.0), rel=0.06)
    lag1 = np.corrcoef(port[1:, 0], port[:-1, 0])[0, 1]
    assert abs(lag1) < 0.06


def test_centre_of_mass_reference_keeps_the_old_model() -> None:
    port, com, _ = _errors(3000, truth_noise_position_m=0.02, truth_noise_attitude_deg=0.0,
                           truth_noise_reference="center_of_mass")
    np.testing.assert_allclose(port, com, atol=1e-12)
    assert com.std(axis=0) == pytest.approx([0.02] * 3, rel=0.07)


def test_correlated_errors_follow_a_first_order_gauss_markov_process() -> None:
    tau = 2.0
    port, _, _ = _errors(20000, truth_noise_position_m=0.02, truth_noise_correlation_s=tau)
    dt = 0.2
    lag1 = np.mean([np.corrcoef(port[1:, i], port[:-1, i])[0, 1] for i in range(3)])
    lag10 = np.mean([np.corrcoef(port[10:, i], port[:-10, i])[0, 1] for i in range(3)])
    assert lag1 == pytest.approx(math.exp(-dt / tau), abs=0.02)
    assert lag10 == pytest.approx(math.exp(-10 * dt / tau), abs=0.05)
    # The stationary spread is still the configured sigma.
    assert port.std(axis=0) == pytest.approx([0.02] * 3, rel=0.12)
