"""Behaviour-cloning warm start: a scripted controller's demonstrations, and a PPO policy fitted
to them before PPO fine-tunes it (:class:`agents.training_config.PretrainConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from agents.training_config import PretrainConfig, TrainingConfig, env_args
from perception.config import MissionConfig

__all__ = ["Demonstrations", "collect_demonstrations", "pretrain_policy"]


@dataclass
class Demonstrations:
    """State-action pairs flown by a scripted controller (see :class:`PretrainConfig`).

    Attributes:
        obs: ``(N, obs_dim)`` raw observations; ``actions``: ``(N, act_dim)`` clean controller
            actions in ``[-1, 1]``; ``rewards``: ``(N,)``; ``episode``: ``(N,)`` episode index;
            ``outcomes``: how each episode ended (its termination cause, or ``truncated``).
    """

    obs: npt.NDArray[np.float32]
    actions: npt.NDArray[np.float32]
    rewards: npt.NDArray[np.float64]
    episode: npt.NDArray[np.int64]
    outcomes: list[str]


def collect_demonstrations(
    cfg: TrainingConfig, mission: MissionConfig, progress: bool = False
) -> Demonstrations:
    """Fly ``cfg.pretrain.controller`` on the training env (seeds ``cfg.seed + 10_000 + k``)."""
    import gymnasium as gym

    from agents.controllers import make_controller

    pre = cfg.pretrain
    if pre is None:
        raise ValueError("collect_demonstrations needs cfg.pretrain")
    env_id, kwargs = env_args(cfg, mission)
    env = gym.make(env_id, **kwargs)
    ctl = make_controller(pre.controller, env.unwrapped.cfg)
    rng = np.random.default_rng(cfg.seed)
    obs_l, act_l, rew_l, ep_l, outcomes = [], [], [], [], []
    episodes = range(pre.episodes)
    if progress:
        from tqdm.auto import tqdm

        episodes = tqdm(episodes, desc="demonstrations", unit="ep")
    try:
        for k in episodes:
            reset = getattr(ctl, "reset", None)
            if callable(reset):
                reset()
            obs, _ = env.reset(seed=cfg.seed + 10_000 + k)
            while True:
                label = np.clip(np.asarray(ctl(obs), dtype=np.float32), -1.0, 1.0)
                act = label + pre.action_noise * rng.standard_normal(label.shape).astype(np.float32)
                obs_l.append(obs)
                act_l.append(label)
                ep_l.append(k)
                obs, r, term, trunc, info = env.step(np.clip(act, -1.0, 1.0))
                rew_l.append(float(r))
                if term or trunc:
                    outcomes.append(info["termination"] if term else "truncated")
                    break
    finally:
        env.close()
    return Demonstrations(np.asarray(obs_l, np.float32), np.asarray(act_l, np.float32),
                          np.asarray(rew_l), np.asarray(ep_l, np.int64), outcomes)


def pretrain_policy(model: Any, vec: Any, demos: Demonstrations, pre: PretrainConfig, gamma: float,
                    seed: int) -> dict[str, Any]:
    """Behaviour cloning of a PPO ``model`` on ``demos`` (see :class:`PretrainConfig`).

    Initialises ``vec``'s observation (and return) statistics from the demonstrations, fits the
    policy mean to the actions and the value head to the normalised discounted returns, then
    sets the policy's log standard deviation. Returns the final losses.
    """
    import torch

    obs = demos.obs.astype(np.float64)
    # Reward normalisation as VecNormalize does it: by the spread of the running discounted return.
    running = np.empty_like(demos.rewards)
    ret = 0.0
    for i, (r, ep) in enumerate(zip(demos.rewards, demos.episode)):
        ret = r if i == 0 or ep != demos.episode[i - 1] else ret * gamma + r
        running[i] = ret
    if vec.norm_obs:
        vec.obs_rms.update(obs)
    if vec.norm_reward:
        vec.ret_rms.update(running)
        scale = np.sqrt(vec.ret_rms.var + vec.epsilon)
        r_norm = np.clip(demos.rewards / scale, -vec.clip_reward, vec.clip_reward)
    else:
        r_norm = demos.rewards
    # Discounted return-to-go of each state, per episode (the episodes end by termination).
    targets = np.empty_like(r_norm)
    g = 0.0
    for i in range(len(r_norm) - 1, -1, -1):
        last = i == len(r_norm) - 1 or demos.episode[i + 1] != demos.episode[i]
        g = r_norm[i] if last else r_norm[i] + gamma * g
        targets[i] = g
    policy = model.policy
    x = torch.as_tensor(vec.normalize_obs(obs), dtype=torch.float32)
    y = torch.as_tensor(demos.actions, dtype=torch.float32)
    v = torch.as_tensor(targets, dtype=torch.float32)
    opt = torch.optim.Adam(policy.parameters(), lr=pre.learning_rate)
    gen = torch.Generator().manual_seed(seed)
    policy.set_training_mode(True)
    act_loss = val_loss = float("nan")
    for _ in range(pre.epochs):
        order = torch.randperm(len(x), generator=gen)
        a_sum = v_sum = 0.0
        for start in range(0, len(x), pre.batch_size):
            idx = order[start:start + pre.batch_size]
            mean = policy.get_distribution(x[idx]).distribution.mean
            value = policy.predict_values(x[idx]).flatten()
            la = torch.nn.functional.mse_loss(mean, y[idx])
            lv = torch.nn.functional.mse_loss(value, v[idx])
            opt.zero_grad()
            (la + 0.5 * lv).backward()
            opt.step()
            a_sum += float(la.detach()) * len(idx)
            v_sum += float(lv.detach()) * len(idx)
        act_loss, val_loss = a_sum / len(x), v_sum / len(x)
    policy.set_training_mode(False)
    with torch.no_grad():
        policy.log_std.fill_(pre.log_std)
    docked = sum(o == "docked" for o in demos.outcomes)
    return {
        "controller": pre.controller, "episodes": len(demos.outcomes), "samples": len(x),
        "demo_docked": docked, "action_mse": act_loss, "value_mse": val_loss,
        "log_std": pre.log_std,
    }
