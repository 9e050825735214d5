"""One closed-loop episode: a controller (or policy) flies an env; a tidy record comes back.

Used by the demo, ``tridar-env run``, campaigns and ``evaluate`` so that every summary is computed
the same way. The controller sees only observations; truth from ``info`` goes into the log.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import numpy.typing as npt

Policy = Callable[[npt.NDArray[np.float32]], npt.ArrayLike]

#: Termination causes that count as success (docking, or a fly-around completed).
SUCCESS_CAUSES = ("docked", "completed")

#: Columns of the per-step log.
LOG_COLUMNS = (
    "t", "mode", "range_true", "x_lvlh", "y_lvlh", "z_lvlh", "vx_lvlh", "vy_lvlh", "vz_lvlh",
    "est_pos_err_m", "est_att_err_deg", "n_points", "reward", "propellant_kg", "delta_v",
    "ax", "ay", "az", "axial_distance", "lateral_offset", "closing_speed",
)


@dataclass
class EpisodeResult:
    """Outcome and statistics of one episode.

    Attributes:
        seed: reset seed.
        outcome: ``docked``, a failure cause (``collision``, ``out_of_bounds``, ``out_of_fuel``,
            ``corridor_exit``) or ``timeout``.
        steps, sim_time_s, delta_v_m_s, propellant_used_kg, episode_return: totals.
        contact: final contact geometry (``ContactState`` fields) at the end.
        max_pos_err_m, rms_pos_err_m, max_att_err_deg, rms_att_err_deg: estimation errors over
            the steps with a valid pose.
        time_in_mode_s: seconds spent in each TriDAR mode.
        acquisitions: number of search -> tracking transitions.
        track_losses: the TriDAR's declared losses of track (0 without the pipeline).
        symmetry_switches: tracks the ambiguity monitor moved to a near-symmetric twin.
        pose_fraction: fraction of steps whose state vector carries a pose (position and
            attitude valid), degraded or not: the tracking availability.
        hmi_steps: steps whose pose is valid and not degraded but whose docking-port error
            exceeds the published protection level (hazardously misleading).
        restarts: planned restarts of the pipeline; ``restarts_reacquired``: those followed by a
            pose again before the episode ended; ``restarts_pending``: 1 when the last restart
            had not yet published a pose when the episode ended (a fly-around completed 2 s
            after a restart, its new track acquired and its first pose still in the sensor's
            latency), else 0.
        log: per-step columns (:data:`LOG_COLUMNS`) when ``keep_log``.
    """

    seed: int
    outcome: str
    steps: int
    sim_time_s: float
    delta_v_m_s: float
    propellant_used_kg: float
    episode_return: float
    contact: dict[str, float]
    max_pos_err_m: float
    rms_pos_err_m: float
    max_att_err_deg: float
    rms_att_err_deg: float
    time_in_mode_s: dict[str, float]
    acquisitions: int
    track_losses: int = 0
    symmetry_switches: int = 0
    pose_fraction: float = float("nan")
    hmi_steps: int = 0
    restarts: int = 0
    restarts_reacquired: int = 0
    restarts_pending: int = 0
    log: dict[str, list[Any]] = field(default_factory=dict, repr=False)

    @property
    def docked(self) -> bool:
        return self.outcome == "docked"

    @property
    def success(self) -> bool:
        """The task's goal reached: docked, or a fly-around completed."""
        return self.outcome in SUCCESS_CAUSES

    def row(self) -> dict[str, Any]:
        """A flat dict for tables and Parquet (no per-step log)."""
        d = asdict(self)
        d.pop("log")
        contact = d.pop("contact")
        modes = d.pop("time_in_mode_s")
        d.update({f"contact_{k}": v for k, v in contact.items()})
        d.update({f"time_{k}_s": modes.get(k, 0.0) for k in ("bearing", "search", "tracking")})
        return d


def _nan_stats(values: list[float]) -> tuple[float, float]:
    a = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    if a.size == 0:
        return float("nan"), float("nan")
    return float(a.max()), float(np.sqrt(np.mean(a**2)))


def run_episode(
    env: gym.Env,
    policy: Policy,
    seed: int,
    *,
    keep_log: bool = False,
    max_steps: int | None = None,
    on_step: Callable[[int], None] | None = None,
    on_frame: Callable[[npt.NDArray[np.uint8]], None] | None = None,
) -> EpisodeResult:
    """Fly one episode and summarise it.

    Args:
        env: a (possibly wrapped) ``DockingEnv``.
        policy: ``obs -> action``; a controller object with ``reset()`` is reset first.
        seed: the reset seed (the whole episode is a function of it).
        keep_log: keep the per-step log in the result.
        max_steps: stop (outcome ``timeout``) after this many steps even without truncation.
        on_step: called with the step index (progress bars).
        on_frame: called with ``env.render()`` output each step (video), when rendering.
    """
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()
    obs, info = env.reset(seed=seed)
    prop0 = float(info["propellant_kg"])
    log: dict[str, list[Any]] = {c: [] for c in LOG_COLUMNS}
    pos_err: list[float] = []
    att_err: list[float] = []
    modes: dict[str, float] = {}
    port = np.append(np.asarray(env.unwrapped.target.T_target_port[:3, 3], dtype=np.float64), 1.0)
    stats_of = getattr(getattr(env.unwrapped, "observer", None), "pipeline", None)
    pose_steps = hmi = reacquired = 0
    restarts_seen = 0
    awaiting_pose = False
    acquisitions = 0
    prev_mode = info["mode"]
    total = 0.0
    steps = 0
    outcome = "timeout"
    while True:
        action = np.asarray(policy(obs), dtype=np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        total += float(reward)
        mode = info["mode"]
        modes[mode] = modes.get(mode, 0.0) + float(info.get("step_dt", 0.0))
        sv = env.unwrapped.state_vector
        n_restarts = int(getattr(getattr(stats_of, "stats", None), "restarts", 0))
        if n_restarts > restarts_seen:
            restarts_seen, awaiting_pose = n_restarts, True
        if sv is not None and sv.valid.position and sv.valid.attitude:
            pose_steps += 1
            if awaiting_pose:
                reacquired, awaiting_pose = reacquired + 1, False
            if not sv.valid.degraded:
                err = sv.T_sensor_target @ port - info["truth_T_sensor_target"] @ port
                hmi += bool(np.linalg.norm(err[:3]) > sv.protection_level)
        if mode == "tracking" and prev_mode != "tracking":
            acquisitions += 1
        prev_mode = mode
        pos_err.append(info.get("estimate_position_error_m", float("nan")))
        att_err.append(info.get("estimate_attitude_error_deg", float("nan")))
        if keep_log:
            r, v, c = info["truth_r_lvlh"], info["truth_v_lvlh"], info["contact"]
            row = (
                info["t"], mode, float(np.linalg.norm(info["truth_T_sensor_target"][:3, 3])),
                *r, *v, info.get("estimate_position_error_m", float("nan")), info.get("estimate_attitude_error_deg", float("nan")),
                info["n_points"], float(reward), info["propellant_kg"], info["delta_v"],
                *np.asarray(action[:3], dtype=float), c.axial_distance, c.lateral_offset,
                c.closing_speed,
            )
            for k, val in zip(LOG_COLUMNS, row):
                log[k].append(val)
        if on_step is not None:
            on_step(steps)
        if on_frame is not None:
            frame = env.render()
            if frame is not None:
                on_frame(frame)
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            outcome = info["termination"] if terminated else "timeout"
            break
    mp, rp = _nan_stats(pos_err)
    ma, ra = _nan_stats(att_err)
    stats = getattr(getattr(getattr(env.unwrapped, "observer", None), "pipeline", None), "stats", None)
    return EpisodeResult(
        seed=int(seed), outcome=outcome, steps=steps, sim_time_s=float(info["t"]),
        delta_v_m_s=float(info["delta_v"]), propellant_used_kg=prop0 - float(info["propellant_kg"]),
        episode_return=total, contact=asdict(info["contact"]),
        max_pos_err_m=mp, rms_pos_err_m=rp, max_att_err_deg=ma, rms_att_err_deg=ra,
        time_in_mode_s=modes, acquisitions=acquisitions,
        track_losses=int(getattr(stats, "losses", 0)),
        symmetry_switches=int(getattr(stats, "symmetry_switches", 0)),
        pose_fraction=pose_steps / steps if steps else float("nan"),
        hmi_steps=hmi, restarts=restarts_seen, restarts_reacquired=reacquired,
        restarts_pending=int(awaiting_pose),
        log=log if keep_log else {},
    )


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95% by default)."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    den = 1.0 + z**2 / n
    centre = (p + z**2 / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / den
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))
