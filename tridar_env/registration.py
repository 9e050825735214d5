"""Gymnasium ids of tridar-env; ``import tridar_env`` registers them.

========================  ==========================================  =================
id                        scenario (``configs/missions/*.yaml``)      max_episode_steps
========================  ==========================================  =================
TriDAR/FinalApproach-v0   final_approach: ISS-like port, V-bar, 30 m  3000 (10 min)
TriDAR/TumblingTarget-v0  tumbling_target: cygnss spinning, 60 m      6000 (20 min)
TriDAR/Rendezvous-v0      rendezvous: from 500 m in bearing mode      20000
========================  ==========================================  =================

``gymnasium.make(id, config=path_or_overrides, perception="truth", **overrides)`` passes its
keyword arguments to :class:`~tridar_env.env.DockingEnv`; a ``config`` dict is a set of overrides on
the id's mission file. ``gymnasium.make_vec(id, num_envs, vectorization_mode="vector_entry_point",
perception="truth")`` builds :class:`~tridar_env.vector.TruthVectorEnv`, which steps all the
environments as arrays (truth and truth-plus-noise perception only).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from perception.config import config_path, load_config

ENV_IDS: dict[str, str] = {
    "TriDAR/FinalApproach-v0": "final_approach",
    "TriDAR/TumblingTarget-v0": "tumbling_target",
    "TriDAR/Rendezvous-v0": "rendezvous",
}


def mission_source(mission: str | None, config: Any = None) -> tuple[Any, dict[str, Any]]:
    """What an id's entry point loads: ``(config source, overrides)``. A path, mission name or
    ``MissionConfig`` stands on its own; None or an overrides dict goes on the id's mission file."""
    if config is None or isinstance(config, dict):
        if mission is None:
            raise ValueError("mission=None and config is not a file; expected a mission name or config")
        return config_path(mission), dict(config or {})
    return config, {}


def make_mission_env(mission: str, config: Any = None, **kwargs: Any) -> Any:
    """Entry point: the id's mission file, with ``config`` (a path or overrides dict) on top."""
    from tridar_env.env import DockingEnv

    source, overrides = mission_source(mission, config)
    return DockingEnv(source, **overrides, **kwargs)


def register_envs() -> None:
    """Register every id (idempotent)."""
    for env_id, mission in ENV_IDS.items():
        if env_id in gym.registry:
            continue
        steps = load_config(config_path(mission)).env.max_episode_steps
        gym.register(
            id=env_id,
            entry_point="tridar_env.registration:make_mission_env",
            vector_entry_point="tridar_env.vector:TruthVectorEnv",
            max_episode_steps=steps,
            kwargs={"mission": mission},
        )
