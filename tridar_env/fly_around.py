"""The fly-around task (``env.task: fly_around``, ``TriDAR/FlyAround-v0``): its bookkeeping,
termination and reward terms; :class:`~tridar_env.env.DockingEnv` delegates to it.

Completing the fly-around means sweeping ``env.fly_around.sweep_deg`` about the target's centre of
mass in the orbital plane (the chaser's phase ``atan2(y, x)`` in LVLH, unwrapped, counted in
``direction``) and being inside the standoff band (``standoff_m +- band_m``) when it is reached:
``completed``. Entering the keep-out sphere outside the departure cone about the port axis ends
the episode (``keep_out``), as does touching the hull (``collision``), leaving ``max_range_m``
(``out_of_bounds``) or running dry (``out_of_fuel``).

Rewards (``env.fly_around_reward``, each in ``info["reward_<name>"]``, summing to the reward):
``sweep`` per radian swept (potential-based: the total is the swept angle, whatever the path),
``band`` per second per metre outside the standoff band, ``time`` per second, ``fuel`` per kg,
``success`` on completion, ``keep_out`` on entering the keep-out sphere or touching the hull,
``exit`` on leaving the bounds.
"""

from __future__ import annotations

import math
from typing import Any

from perception.config import EnvConfig
from tridar_env.world import World

__all__ = ["FlyAroundTask"]


class FlyAroundTask:
    """Swept angle, termination and rewards of a fly-around.

    Args:
        env: the environment configuration (``fly_around``, ``fly_around_reward``, ``max_range_m``).
    """

    def __init__(self, env: EnvConfig) -> None:
        self.env = env
        self.swept = 0.0  # [rad]
        self._phase = 0.0
        self._rewarded = 0.0  # swept angle already rewarded [rad]

    def reset(self, world: World) -> None:
        self.swept = 0.0
        self._rewarded = 0.0
        self._phase = self.phase(world)

    @staticmethod
    def phase(world: World) -> float:
        """The chaser's direction about the target's centre of mass in the orbital plane [rad]."""
        r = world.state
        return math.atan2(float(r[1]), float(r[0]))

    def after_frame(self, world: World) -> None:
        """Accumulate the swept angle over one frame (a frame turns far less than half a turn)."""
        phase = self.phase(world)
        d = (phase - self._phase + math.pi) % (2.0 * math.pi) - math.pi
        self.swept += self.env.fly_around.direction * d
        self._phase = phase

    def keep_out_violated(self, world: World) -> bool:
        """Inside the keep-out sphere and outside the departure cone about the port axis."""
        fa = self.env.fly_around
        r = world.state[:3]
        if math.sqrt(float(r @ r)) >= fa.keep_out_radius_m:
            return False
        T_lp = world.T_lvlh_port
        d = world.T_lvlh_dock[:3, 3] - T_lp[:3, 3]
        axial = float(d @ T_lp[:3, 2])
        off = math.degrees(math.atan2(math.sqrt(max(float(d @ d) - axial * axial, 0.0)), axial))
        return off > fa.keep_out_axis_deg

    def termination(self, world: World) -> str:
        fa = self.env.fly_around
        if world.hull_touches():
            return "collision"
        r = world.state[:3]
        rn = math.sqrt(float(r @ r))
        if rn > self.env.max_range_m:
            return "out_of_bounds"
        if self.keep_out_violated(world):
            return "keep_out"
        if math.degrees(self.swept) >= fa.sweep_deg and abs(rn - fa.standoff_m) <= fa.band_m:
            return "completed"
        if world.mass.propellant_kg <= 0.0:
            return "out_of_fuel"
        return ""

    def reward_terms(self, world: World, cause: str, fuel_used: float, dt: float) -> dict[str, float]:
        rw, fa = self.env.fly_around_reward, self.env.fly_around
        r = world.state[:3]
        outside = max(0.0, abs(math.sqrt(float(r @ r)) - fa.standoff_m) - fa.band_m)
        sweep = self.swept - self._rewarded
        self._rewarded = self.swept
        return {
            "reward_sweep": rw.sweep * sweep,
            "reward_band": -rw.band * outside * dt,
            "reward_time": -rw.time * dt,
            "reward_fuel": -rw.fuel * fuel_used,
            "reward_success": rw.success if cause == "completed" else 0.0,
            "reward_keep_out": -rw.keep_out if cause in ("keep_out", "collision") else 0.0,
            "reward_exit": -rw.exit if cause == "out_of_bounds" else 0.0,
        }

    def info(self, world: World) -> dict[str, Any]:
        r = world.state[:3]
        return {
            "swept_deg": math.degrees(self.swept),
            "standoff_error_m": math.sqrt(float(r @ r)) - self.env.fly_around.standoff_m,
        }
