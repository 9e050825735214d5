"""Behaviour-cloning warm start: a scripted controller's demonstrations, and a PPO policy fitted
to them before PPO fine-tunes it, optionally with DAgger rounds (the policy flies, the controller
labels the states it visits) (:class:`agents.training_config.PretrainConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import numpy.typing as npt

from agents.training_config import PretrainConfig, TrainingConfig, env_args
from perception.config import MissionConfig

__all__ = ["Demonstrations", "collect_demonstrations", "dagger", "freeze_obs_stats", "pretrain_policy"]


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
    pre = cfg.pretrain
    if pre is None:
        raise ValueError("collect_demonstrations needs cfg.pretrain")
    seeds = [cfg.seed + 10_000 + k for k in range(pre.episodes)]
    return fly_labelled(cfg, mission, seeds, np.random.default_rng(cfg.seed), progress=progress)


def fly_labelled(cfg: TrainingConfig, mission: MissionConfig, seeds: list[int], rng: np.random.Generator,
                 policy: Callable[[npt.NDArray[np.float32]], npt.NDArray[np.float32]] | None = None,
                 progress: bool = False, desc: str = "demonstrations") -> Demonstrations:
    """Episodes of the training env at reset ``seeds``, every state labelled with the action of
    ``cfg.pretrain.controller`` (clipped to ``[-1, 1]``).

    The executed action is the label (``policy`` None: demonstrations) or ``policy(obs)`` of the
    full observation (DAgger: the controller runs alongside on the same observations, so its
    filters and phases follow the flight, and a controller with an ``executed(action, obs)``
    method is told the action flown; one without believes its own was), plus Gaussian
    ``action_noise`` from ``rng``.
    """
    import gymnasium as gym

    from agents.controllers import make_controller

    pre = cfg.pretrain
    assert pre is not None
    env_id, kwargs = env_args(cfg, mission)
    env = gym.make(env_id, **kwargs)
    ctl = make_controller(pre.controller, env.unwrapped.cfg)
    obs_l, act_l, rew_l, ep_l, outcomes = [], [], [], [], []
    episodes: Any = range(len(seeds))
    if progress:
        from tqdm.auto import tqdm

        episodes = tqdm(episodes, desc=desc, unit="ep")
    try:
        for k in episodes:
            reset = getattr(ctl, "reset", None)
            if callable(reset):
                reset()
            obs, _ = env.reset(seed=seeds[k])
            while True:
                label = np.clip(np.asarray(ctl(obs), dtype=np.float32), -1.0, 1.0)
                act = label if policy is None else np.asarray(policy(obs), dtype=np.float32)
                act = act + pre.action_noise * rng.standard_normal(label.shape).astype(np.float32)
                act = np.clip(act, -1.0, 1.0)
                if policy is not None and callable(getattr(ctl, "executed", None)):
                    ctl.executed(act, obs)
                obs_l.append(obs)
                act_l.append(label)
                ep_l.append(k)
                obs, r, term, trunc, info = env.step(act)
                rew_l.append(float(r))
                if term or trunc:
                    outcomes.append(info["termination"] if term else "truncated")
                    break
    finally:
        env.close()
    return Demonstrations(np.asarray(obs_l, np.float32), np.asarray(act_l, np.float32),
                          np.asarray(rew_l), np.asarray(ep_l, np.int64), outcomes)


def dagger(model: Any, vec: Any, demos: Demonstrations, cfg: TrainingConfig, mission: MissionConfig,
           indices: npt.NDArray[np.intp] | None = None, progress: bool = False) -> list[dict[str, Any]]:
    """``cfg.pretrain.dagger_rounds`` rounds of DAgger on a cloned PPO ``model`` (see
    :class:`PretrainConfig`): each round the policy's mean action flies ``dagger_episodes``
    episodes (reset seeds after the demonstrations'), the controller labels them, and the policy
    mean is fitted to every labelled state so far. ``demos``: the cloning's demonstrations (the
    policy's observation: ``indices`` of the full one, or all of it). Returns each round's
    outcomes and final action error.
    """
    pre = cfg.pretrain
    assert pre is not None
    rng = np.random.default_rng([cfg.seed, 1])
    obs, act = demos.obs, demos.actions

    from agents.validation import mean_action

    def act_of(o: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        return mean_action(model, vec, o, indices)

    rounds = []
    first = cfg.seed + 10_000 + pre.episodes
    for r in range(pre.dagger_rounds):
        seeds = [first + r * pre.dagger_episodes + k for k in range(pre.dagger_episodes)]
        new = fly_labelled(cfg, mission, seeds, rng, policy=act_of, progress=progress,
                           desc=f"DAgger round {r + 1}/{pre.dagger_rounds}")
        new_obs = new.obs if indices is None else new.obs[:, indices]
        if vec.norm_obs:
            vec.obs_rms.update(new_obs.astype(np.float64))
        obs, act = np.concatenate([obs, new_obs]), np.concatenate([act, new.actions])
        loss = _fit(model.policy, vec.normalize_obs(obs.astype(np.float64)), act, None, pre,
                    pre.dagger_epochs, cfg.seed + 1 + r)
        rounds.append({"round": r + 1, "episodes": len(new.outcomes),
                       "policy_docked": sum(o == "docked" for o in new.outcomes),
                       "samples": len(obs), "action_mse": loss[0]})
    return rounds


def _fit(policy: Any, x_np: Any, y_np: Any, v_np: Any, pre: PretrainConfig, epochs: int,
         seed: int) -> tuple[float, float]:
    """Fit the policy mean to ``y_np`` (and the value head to ``v_np`` unless None) on the
    normalised observations ``x_np``, ``epochs`` passes of Adam; the last pass's mean losses."""
    import torch

    x = torch.as_tensor(x_np, dtype=torch.float32)
    y = torch.as_tensor(y_np, dtype=torch.float32)
    v = None if v_np is None else torch.as_tensor(v_np, dtype=torch.float32)
    opt = torch.optim.Adam(policy.parameters(), lr=pre.learning_rate)
    gen = torch.Generator().manual_seed(seed)
    policy.set_training_mode(True)
    act_loss = val_loss = float("nan")
    for _ in range(epochs):
        order = torch.randperm(len(x), generator=gen)
        a_sum = v_sum = 0.0
        for start in range(0, len(x), pre.batch_size):
            idx = order[start:start + pre.batch_size]
            mean = policy.get_distribution(x[idx]).distribution.mean
            loss = la = torch.nn.functional.mse_loss(mean, y[idx])
            if v is not None:
                lv = torch.nn.functional.mse_loss(policy.predict_values(x[idx]).flatten(), v[idx])
                loss = la + 0.5 * lv
                v_sum += float(lv.detach()) * len(idx)
            opt.zero_grad()
            loss.backward()
            opt.step()
            a_sum += float(la.detach()) * len(idx)
        act_loss, val_loss = a_sum / len(x), (v_sum / len(x) if v is not None else float("nan"))
    policy.set_training_mode(False)
    return act_loss, val_loss


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
    act_loss, val_loss = _fit(policy, vec.normalize_obs(obs), demos.actions, targets, pre, pre.epochs, seed)
    with torch.no_grad():
        policy.log_std.fill_(pre.log_std)
    docked = sum(o == "docked" for o in demos.outcomes)
    return {
        "controller": pre.controller, "episodes": len(demos.outcomes), "samples": len(demos.obs),
        "demo_docked": docked, "action_mse": act_loss, "value_mse": val_loss,
        "log_std": pre.log_std,
    }


def freeze_obs_stats(vec: Any) -> None:
    """Keep ``vec``'s (a VecNormalize) observation statistics where they are from now on: its
    running mean and variance no longer update (``PretrainConfig.freeze_obs_stats``)."""
    from stable_baselines3.common.running_mean_std import RunningMeanStd

    class FrozenStats(RunningMeanStd):  # type: ignore[misc]
        def update(self, arr: Any) -> None:
            """Nothing: the statistics stay as they are."""

    rms = vec.obs_rms
    frozen = FrozenStats(shape=rms.mean.shape)
    frozen.mean, frozen.var, frozen.count = rms.mean.copy(), rms.var.copy(), rms.count
    vec.obs_rms = frozen
