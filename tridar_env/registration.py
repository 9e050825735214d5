"""Gymnasium ids of tridar-env; ``import tridar_env`` registers them.

========================  ==========================================  =================
id                        scenario (``configs/missions/*.yaml``)      max_episode_steps
========================  ==========================================  =================
TriDAR/FinalApproach-v0   final_approach: ISS-like port, V-bar, 30 m  3000 (10 min)
TriDAR/TumblingTarget-v0  tumbling_target: cygnss spinning, 60 m      6000 (20 min)
TriDAR/Rendezvous-v0      rendezvous: from 500 m in bearing mode      20000
TriDAR/FarRendezvous-v0   far_rendezvous: from 5 km, thermal bearing  20000 (steps lengthen)
TriDAR/FlyAround-v0       fly_around: undock, circle at 100 m         12000
TriDAR/Seed003-v0         seed003: tumbling cygnss, flash LiDAR       6000
========================  ==========================================  =================

``gymnasium.make(id, config=path_or_overrides, perception="truth", **overrides)`` passes its
keyword arguments to :class:`~tridar_env.env.DockingEnv`; a ``config`` dict is a set of overrides on
the id's mission file. ``gymnasium.make_vec(id, num_envs, vectorization_mode="vector_entry_point",
perception="truth")`` builds :class:`~tridar_env.vector.TruthVectorEnv`, which steps all the
environments as arrays (truth and truth-plus-noise perception only).

The time limit is the resolved mission's ``env.max_episode_steps``: the entry point wraps the env
in ``TimeLimit`` with it, so ``config={"env__max_episode_steps": 10}`` (or ``{"env":
{"max_episode_steps": 10}}``, or ``env__max_episode_steps=10``) truncates at 10 steps, and
``env.spec.max_episode_steps`` says so. The ids are registered without a limit of their own for
that reason (Gymnasium's would be fixed at registration, whatever the config). ``gymnasium.make``'s
own ``max_episode_steps=N`` adds its ``TimeLimit`` outside, which can only shorten an episode: the
observation's ``time_fraction`` counts against the mission's limit, so lengthen it there.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from perception.config import config_path

ENV_IDS: dict[str, str] = {
    "TriDAR/FinalApproach-v0": "final_approach",
    "TriDAR/TumblingTarget-v0": "tumbling_target",
    "TriDAR/Rendezvous-v0": "rendezvous",
    "TriDAR/FarRendezvous-v0": "far_rendezvous",
    "TriDAR/FlyAround-v0": "fly_around",
    "TriDAR/Seed003-v0": "seed003",
}


def bare_id(env_id: str) -> str:
    """``TriDAR/FinalApproach-v0`` from ``tridar_env:TriDAR/FinalApproach-v0`` (or itself)."""
    return env_id.split(":", 1)[1] if ":" in env_id else env_id


def mission_source(mission: str | None, config: Any = None) -> tuple[Any, dict[str, Any]]:
    """What an id's entry point loads: ``(config source, overrides)``. A path, mission name or
    ``MissionConfig`` stands on its own; None or an overrides dict goes on the id's mission file."""
    if config is None or isinstance(config, dict):
        if mission is None:
            raise ValueError("mission=None and config is not a file; expected a mission name or config")
        return config_path(mission), dict(config or {})
    return config, {}


def make_mission_env(
    mission: str, config: Any = None, *, render_mode: str | None = None, **overrides: Any
) -> gym.Env[Any, Any]:
    """Entry point: the id's mission file with ``config`` (a path, or an overrides dict whose keys
    are overrides whatever they are named) and ``overrides`` on top, in a ``TimeLimit`` of the
    resolved ``env.max_episode_steps``."""
    from gymnasium.wrappers import TimeLimit

    from tridar_env.env import DockingEnv, _resolve_config

    source, file_overrides = mission_source(mission, config)
    perception = overrides.pop("perception", None)
    if perception is not None:
        overrides["env__perception"] = perception
    env = DockingEnv(_resolve_config(source, {**file_overrides, **overrides}), render_mode=render_mode)
    return TimeLimit(env, env.cfg.env.max_episode_steps)


def register_envs() -> None:
    """Register every id (idempotent); the time limit comes with the env (module docstring)."""
    for env_id, mission in ENV_IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point="tridar_env.registration:make_mission_env",
            vector_entry_point="tridar_env.vector:TruthVectorEnv",
            max_episode_steps=None,
            kwargs={"mission": mission},
        )
