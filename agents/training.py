"""Learning: train a stable-baselines3 policy from a training YAML, and evaluate saved policies.

Intended workflow (the reason for the three perception modes):

1. Measure the TriDAR pipeline's estimation errors:
   ``tridar-env campaign configs/campaigns/pipeline_errors.yaml`` (the summary's RMS position and
   attitude errors; ``plots/error_vs_range.png`` shows how they grow with range).
2. Put those numbers into the training YAML as ``env__truth_noise_*`` and train on
   ``perception: truth+noise``, which is orders of magnitude cheaper than the pipeline:
   ``tridar-env train configs/training/ppo_final_approach.yaml``.
3. Evaluate the saved policy on the full pipeline, with the same summary table as a campaign:
   ``tridar-env evaluate runs/train/ppo_final_approach --perception tridar --episodes 100``
   (or fly it in a distributed campaign with ``controller: sb3:runs/train/ppo_final_approach``).

A training run writes, into its folder: ``model.zip`` (SB3), ``vecnormalize.npz`` (observation and
return statistics as plain arrays, so that evaluation never unpickles them), ``training.yaml`` (the
resolved config), ``checkpoints/`` (model + statistics every ``checkpoint_every_steps``) and
``tb/`` (TensorBoard logs). The folder carries the marker of :mod:`agents.outputs`: ``--force``
replaces those files only, and only in a folder ``train`` created.

Loading a policy (:func:`load_policy`) checks that the file is a zip with SB3's members and hands
SB3 replacements for every pickled field of the archive, so that no user-supplied bytes are
unpickled; the network weights are read by ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import inspect
import json
import re
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

from agents.outputs import atomic_write, check_folder, check_name, claim_folder, lock_folder
from perception.config import ConfigError, MissionConfig, config_path, load_config, save_config

__all__ = [
    "Demonstrations",
    "NormalizeConfig",
    "PretrainConfig",
    "SB3Policy",
    "TrainResult",
    "TrainingConfig",
    "collect_demonstrations",
    "evaluate",
    "load_policy",
    "load_training",
    "pretrain_policy",
    "train",
    "validate_training",
]

MODEL_FILE = "model.zip"
STATS_FILE = "vecnormalize.npz"
CONFIG_FILE = "training.yaml"
PRETRAIN_FILE = "pretrain.json"
CHECKPOINT_DIR = "checkpoints"
#: Marker kind of a training run folder (:mod:`agents.outputs`).
KIND = "train"
_CHECKPOINT_RE = re.compile(r"^(model|vecnormalize)_\d+_steps\.(zip|npz)$")
#: Members every SB3 model archive has.
SB3_MEMBERS = ("data", "policy.pth")


class NormalizeConfig(BaseModel):
    """``VecNormalize`` settings (running mean/variance of observations and returns)."""

    model_config = ConfigDict(extra="forbid")

    obs: bool = True
    reward: bool = True
    clip_obs: Annotated[float, Field(gt=0)] = 10.0
    clip_reward: Annotated[float, Field(gt=0)] = 10.0


class PretrainConfig(BaseModel):
    """Behaviour-cloning warm start from a scripted controller (PPO only).

    Before PPO starts, ``controller`` flies ``episodes`` episodes of the training env (its
    executed actions perturbed by Gaussian ``action_noise`` so that the demonstrations also show
    how to recover from small mistakes; the labels are the controller's clean actions). The
    observation statistics of ``VecNormalize`` are initialised from those states, the policy mean
    is fitted to the actions (mean squared error) and the value head to the demonstrations'
    normalised discounted returns, for ``epochs`` passes; the policy's log standard deviation is
    then set to ``log_std``. PPO fine-tunes from there on the env's reward; during its first
    ``critic_warmup_steps`` steps only the value function learns (the actor is frozen), so that
    the first policy updates use advantages from a critic fitted to the env's own returns.
    """

    model_config = ConfigDict(extra="forbid")

    controller: str = "glideslope"
    episodes: Annotated[int, Field(ge=1)] = 100
    action_noise: Annotated[float, Field(ge=0)] = 0.1
    epochs: Annotated[int, Field(ge=1)] = 40
    batch_size: Annotated[int, Field(ge=1)] = 256
    learning_rate: Annotated[float, Field(gt=0)] = 1e-3
    log_std: float = -2.5
    critic_warmup_steps: Annotated[int, Field(ge=0)] = 0


class TrainingConfig(BaseModel):
    """A training run (one YAML file in ``configs/training``).

    Attributes:
        name: run name (default output folder ``runs/train/<name>``, TensorBoard run name): a plain
            folder name (letters, digits, ``.``, ``_``, ``-``).
        algo: ``ppo`` or ``sac``.
        env_id: registered id; ``mission`` optionally replaces its mission file.
        perception: what the policy sees while training (``truth+noise`` is the intended mode).
        config: mission-config overrides, ``__``-nested (e.g. ``env__truth_noise_position_m``),
            used in training and by default in :func:`evaluate`.
        train_config: overrides applied on top of ``config`` only while training (e.g. a wider
            start distribution as a curriculum); evaluation flies the mission without them.
        total_timesteps: environment steps over all envs.
        n_envs: parallel envs; ``vec_env`` ``subproc`` (one process each) or ``dummy``.
        seed: seeds SB3, torch and the envs (env ``k`` gets ``seed + k``).
        normalize: VecNormalize settings.
        checkpoint_every_steps: save model + statistics every this many total steps (None: off).
        net_arch, activation, log_std_init: policy network.
        hyperparams: keyword arguments of the SB3 algorithm (``learning_rate``, ``n_steps``, ...).
        pretrain: optional behaviour-cloning warm start (:class:`PretrainConfig`, PPO only).
        device: torch device; ``torch_threads``: intra-op threads of the learner.
    """

    model_config = ConfigDict(extra="forbid")

    name: str = "policy"
    algo: Literal["ppo", "sac"] = "ppo"
    env_id: str = "TriDAR/FinalApproach-v0"
    mission: str | None = None
    perception: Literal["truth", "truth+noise", "tridar"] = "truth+noise"
    config: dict[str, Any] = Field(default_factory=dict)
    train_config: dict[str, Any] = Field(default_factory=dict)
    total_timesteps: Annotated[int, Field(ge=1)] = 1_000_000
    n_envs: Annotated[int, Field(ge=1, le=256)] = 2
    vec_env: Literal["subproc", "dummy"] = "subproc"
    seed: Annotated[int, Field(ge=0)] = 0
    normalize: NormalizeConfig = NormalizeConfig()
    checkpoint_every_steps: Annotated[int, Field(ge=1)] | None = 100_000
    net_arch: list[Annotated[int, Field(ge=1)]] | None = None
    activation: Literal["tanh", "relu", "elu", "leaky_relu"] | None = None
    log_std_init: float | None = None
    hyperparams: dict[str, Any] = Field(default_factory=dict)
    pretrain: PretrainConfig | None = None
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    torch_threads: Annotated[int, Field(ge=1)] = 1


# Keyword arguments the trainer sets itself (not allowed in ``hyperparams``).
_RESERVED = {"policy", "env", "seed", "verbose", "tensorboard_log", "policy_kwargs", "device",
             "_init_setup_model"}


def _algo_class(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def _bare_id(env_id: str) -> str:
    return env_id.split(":", 1)[1] if ":" in env_id else env_id


def _mission_path(env_id: str, mission: str | None) -> Path:
    from tridar_env.registration import ENV_IDS

    return Path(mission) if mission else config_path(ENV_IDS[_bare_id(env_id)])


def validate_training(cfg: TrainingConfig, source: str = "training config") -> MissionConfig:
    """Check the id, the mission overrides and the hyperparameters; return the mission config.

    Raises:
        ConfigError: naming the field and the value.
    """
    from tridar_env.registration import ENV_IDS

    def fail(msg: str) -> None:
        raise ConfigError(f"{source}: {msg}")

    try:
        check_name(cfg.name)
    except ValueError as exc:
        fail(str(exc))
    if _bare_id(cfg.env_id) not in ENV_IDS:
        fail(f"env_id={cfg.env_id!r} is not registered; expected one of {', '.join(ENV_IDS)}")
    if cfg.pretrain is not None and cfg.algo != "ppo":
        fail(f"pretrain is set with algo={cfg.algo!r}; behaviour cloning is implemented for 'ppo'")
    if cfg.mission is not None and not Path(cfg.mission).is_file():
        fail(f"mission={cfg.mission!r}: no such file")
    params = set(inspect.signature(_algo_class(cfg.algo).__init__).parameters) - _RESERVED - {"self"}
    for key, value in cfg.hyperparams.items():
        if key not in params:
            fail(
                f"hyperparams.{key}={value!r} is not a {cfg.algo.upper()} argument; expected one "
                f"of {', '.join(sorted(params))}"
            )
        if not isinstance(value, (int, float, str, bool, type(None), list)):
            fail(f"hyperparams.{key}={value!r}; expected a number, string, bool or list")
    try:
        mission = load_config(
            _mission_path(cfg.env_id, cfg.mission), **cfg.config, **cfg.train_config,
            env__perception=cfg.perception
        )
    except ConfigError as exc:
        detail = "; ".join(line.strip() for line in str(exc).splitlines()[1:]) or str(exc)
        fail(f"config gives an invalid mission: {detail}")
    if cfg.pretrain is not None:
        from agents.controllers import make_controller

        try:
            make_controller(cfg.pretrain.controller, mission)
        except ValueError as exc:
            fail(f"pretrain.{exc}")
    return mission


def load_training(path: str | Path, **overrides: Any) -> TrainingConfig:
    """Read and validate a training YAML (a bare name is looked up in ``configs/training``)."""
    p = config_path(path, "training")
    cfg = load_config(p, model=TrainingConfig, **overrides)
    validate_training(cfg, str(p))
    return cfg


# ---------------------------------------------------------------------------------------------
# VecNormalize statistics as plain arrays
# ---------------------------------------------------------------------------------------------
def _save_stats(vec: Any, path: Path) -> None:
    arrays = dict(
        obs_mean=vec.obs_rms.mean, obs_var=vec.obs_rms.var, obs_count=vec.obs_rms.count,
        ret_mean=vec.ret_rms.mean, ret_var=vec.ret_rms.var, ret_count=vec.ret_rms.count,
        clip_obs=vec.clip_obs, clip_reward=vec.clip_reward, epsilon=vec.epsilon, gamma=vec.gamma,
        norm_obs=vec.norm_obs, norm_reward=vec.norm_reward,
    )
    # The temporary name ends in .npz: np.savez would append it otherwise.
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")


def _load_stats(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            stats = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path} is not a VecNormalize statistics file ({exc})") from None
    need = {"obs_mean", "obs_var", "clip_obs", "epsilon", "norm_obs"}
    if not need <= set(stats):
        raise ValueError(f"{path} lacks {sorted(need - set(stats))}; expected a file written by train")
    return stats


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------
@dataclass
class TrainResult:
    """Where a training run went.

    Attributes:
        out_dir: run folder; ``model_path``, ``stats_path``: the saved policy and statistics.
        timesteps: steps trained; ``wall_time_s``: time spent; ``interrupted``: Ctrl-C.
    """

    out_dir: Path
    model_path: Path
    stats_path: Path | None
    timesteps: int
    wall_time_s: float
    interrupted: bool = False


def _env_args(cfg: TrainingConfig, mission: MissionConfig) -> tuple[str, dict[str, Any]]:
    env_id = cfg.env_id if ":" in cfg.env_id else f"tridar_env:{cfg.env_id}"
    kwargs = {
        "perception": cfg.perception, "config": cfg.mission,
        "max_episode_steps": mission.env.max_episode_steps,
        **{k: v for k, v in {**cfg.config, **cfg.train_config}.items()
           if k.replace(".", "__") != "env__perception"},
    }
    return env_id, kwargs


def _make_vec_env(cfg: TrainingConfig, mission: MissionConfig) -> Any:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    env_id, kwargs = _env_args(cfg, mission)
    vec_cls = SubprocVecEnv if cfg.vec_env == "subproc" and cfg.n_envs > 1 else DummyVecEnv
    return make_vec_env(env_id, n_envs=cfg.n_envs, seed=cfg.seed, vec_env_cls=vec_cls,
                        env_kwargs=kwargs)


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
    env_id, kwargs = _env_args(cfg, mission)
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


def _policy_kwargs(cfg: TrainingConfig) -> dict[str, Any]:
    import torch

    kw: dict[str, Any] = {}
    if cfg.net_arch is not None:
        kw["net_arch"] = list(cfg.net_arch)
    if cfg.activation is not None:
        kw["activation_fn"] = {
            "tanh": torch.nn.Tanh, "relu": torch.nn.ReLU, "elu": torch.nn.ELU,
            "leaky_relu": torch.nn.LeakyReLU,
        }[cfg.activation]
    if cfg.log_std_init is not None:
        kw["log_std_init"] = cfg.log_std_init
    return kw


def _progress_bar_available() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("tqdm", "rich"))


def _checkpoint_callback(save_freq: int, path: Path, vec: Any) -> Any:
    from stable_baselines3.common.callbacks import CheckpointCallback

    class Checkpoint(CheckpointCallback):
        """SB3's checkpoint plus the normalisation statistics as ``.npz`` (no pickle)."""

        def _on_step(self) -> bool:
            if self.n_calls % self.save_freq == 0:
                _save_stats(vec, Path(self.save_path) / f"vecnormalize_{self.num_timesteps}_steps.npz")
            return super()._on_step()

    return Checkpoint(save_freq=save_freq, save_path=str(path), name_prefix="model")


def _outcome_callback(window: int = 100) -> Any:
    """Log how the last ``window`` training episodes ended (``outcome/<cause>`` in TensorBoard).

    The return alone does not say whether a policy docks or just survives; these fractions
    (docked, collision, corridor_exit, out_of_bounds, out_of_fuel, truncated) do.
    """
    from collections import deque

    from stable_baselines3.common.callbacks import BaseCallback

    from tridar_env.env import CAUSES

    class Outcomes(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.recent: deque[str] = deque(maxlen=window)

        def _on_step(self) -> bool:
            for done, info in zip(self.locals["dones"], self.locals["infos"]):
                if done:
                    cause = info.get("termination") or "truncated"
                    self.recent.append(cause)
            if self.recent:
                for cause in (*CAUSES, "truncated"):
                    self.logger.record(f"outcome/{cause}", self.recent.count(cause) / len(self.recent))
            return True

    return Outcomes()


def _critic_warmup_callback(steps: int) -> Any:
    """Freeze the actor (policy network, action head, log std) for the first ``steps`` steps."""
    from stable_baselines3.common.callbacks import BaseCallback

    class CriticWarmup(BaseCallback):
        def _actor(self) -> list[Any]:
            p = self.model.policy
            return [*p.mlp_extractor.policy_net.parameters(), *p.action_net.parameters(), p.log_std]

        def _on_training_start(self) -> None:
            for param in self._actor():
                param.requires_grad_(False)

        def _on_rollout_start(self) -> None:
            if self.num_timesteps >= steps:
                for param in self._actor():
                    param.requires_grad_(True)

        def _on_step(self) -> bool:
            return True

    return CriticWarmup()


def _save_model(model: Any, path: Path) -> None:
    # Transient training state is left out: it is pickled by SB3 and useless for inference.
    exclude = ["_last_obs", "_last_episode_starts", "_last_original_obs", "ep_info_buffer",
               "ep_success_buffer", "env"]
    atomic_write(path, lambda tmp: model.save(tmp, exclude=exclude), suffix=".zip")


def _discard(out: Path) -> None:
    """``--force``: delete what an earlier ``train`` wrote in ``out`` (known names only; the
    TensorBoard logs stay, SB3 numbers the next run)."""
    for name in (MODEL_FILE, STATS_FILE, CONFIG_FILE, PRETRAIN_FILE):
        (out / name).unlink(missing_ok=True)
    ckpt = out / CHECKPOINT_DIR
    if ckpt.is_dir():
        for p in ckpt.iterdir():
            if _CHECKPOINT_RE.match(p.name) and p.is_file():
                p.unlink()


def train(
    cfg: TrainingConfig, out_dir: str | Path, *, progress: bool = True, force: bool = False
) -> TrainResult:
    """Train ``cfg.algo`` on vectorised, normalised envs and save the policy into ``out_dir``.

    Args:
        cfg: the training run.
        out_dir: run folder (see the module docstring for its contents).
        progress: SB3's progress bar (when tqdm and rich are installed).
        force: replace a policy already in ``out_dir`` (only in a folder ``train`` created).

    Raises:
        ConfigError: invalid config. ValueError: ``out_dir`` holds a model and ``force`` is
            False. OutputFolderError (a ValueError): ``out_dir`` was not created by ``train``
            and is not empty, or another process is writing it.
    """
    import torch
    from stable_baselines3.common.callbacks import CallbackList
    from stable_baselines3.common.vec_env import VecNormalize

    mission = validate_training(cfg)
    out = Path(out_dir)
    check_folder(out, KIND, destroy="--force" if force else None)
    if (out / MODEL_FILE).exists() and not force:
        raise ValueError(f"{out / MODEL_FILE} exists; pass --force to replace it or choose another --out")
    torch.set_num_threads(cfg.torch_threads)
    venv = _make_vec_env(cfg, mission)
    with contextlib.ExitStack() as stack:
        stack.callback(venv.close)
        gamma = float(cfg.hyperparams.get("gamma", 0.99))
        vec = VecNormalize(
            venv, norm_obs=cfg.normalize.obs, norm_reward=cfg.normalize.reward,
            clip_obs=cfg.normalize.clip_obs, clip_reward=cfg.normalize.clip_reward, gamma=gamma,
        )
        tb = str(out / "tb") if importlib.util.find_spec("tensorboard") is not None else None
        model = _algo_class(cfg.algo)(
            "MlpPolicy", vec, seed=cfg.seed, verbose=0, tensorboard_log=tb,
            policy_kwargs=_policy_kwargs(cfg) or None, device=cfg.device, **cfg.hyperparams,
        )
        pretrain_stats = None
        if cfg.pretrain is not None:
            demos = collect_demonstrations(cfg, mission, progress=progress)
            pretrain_stats = pretrain_policy(model, vec, demos, cfg.pretrain, gamma, cfg.seed)
        # The env and model were built: only now does the run folder appear.
        claim_folder(out, KIND)
        stack.enter_context(lock_folder(out))
        if force:
            _discard(out)
        elif (out / MODEL_FILE).exists():  # another run finished meanwhile
            raise ValueError(f"{out / MODEL_FILE} exists; pass --force to replace it or choose another --out")
        atomic_write(out / CONFIG_FILE, lambda p: save_config(cfg, p))
        if pretrain_stats is not None:
            text = json.dumps(pretrain_stats, indent=2) + "\n"
            atomic_write(out / PRETRAIN_FILE, lambda p: p.write_text(text))
        callbacks = [_outcome_callback()]
        if cfg.pretrain is not None and cfg.pretrain.critic_warmup_steps > 0:
            callbacks.append(_critic_warmup_callback(cfg.pretrain.critic_warmup_steps))
        if cfg.checkpoint_every_steps is not None:
            freq = max(cfg.checkpoint_every_steps // cfg.n_envs, 1)
            callbacks.append(_checkpoint_callback(freq, out / CHECKPOINT_DIR, vec))
        t0 = time.perf_counter()
        interrupted = False
        try:
            model.learn(
                total_timesteps=cfg.total_timesteps, callback=CallbackList(callbacks),
                progress_bar=progress and _progress_bar_available(), tb_log_name=cfg.name,
            )
        except KeyboardInterrupt:
            interrupted = True
        wall = time.perf_counter() - t0
        _save_model(model, out / MODEL_FILE)
        _save_stats(vec, out / STATS_FILE)
        return TrainResult(out, out / MODEL_FILE, out / STATS_FILE, int(model.num_timesteps), wall,
                           interrupted)


# ---------------------------------------------------------------------------------------------
# Loading a policy safely
# ---------------------------------------------------------------------------------------------
_FLOAT_RE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?inf")


def _parse_box(item: Any, what: str, path: Path) -> Any:
    """A ``Box`` from the printable fields SB3 stores beside a pickled space."""
    from gymnasium import spaces

    if not isinstance(item, dict) or "Box" not in str(item.get(":type:", "")):
        raise ValueError(f"{path}: {what} is {item.get(':type:') if isinstance(item, dict) else item!r}; "
                         "expected a Box space")
    shape = tuple(int(v) for v in re.findall(r"\d+", str(item.get("_shape", ""))))
    n = int(np.prod(shape)) if shape else 0
    lo = [float(v) for v in _FLOAT_RE.findall(str(item.get("low", "")))]
    hi = [float(v) for v in _FLOAT_RE.findall(str(item.get("high", "")))]
    if not shape or len(lo) != n or len(hi) != n:
        raise ValueError(f"{path}: cannot read the {what} (shape {shape}) of this model")
    return spaces.Box(np.array(lo, np.float32).reshape(shape), np.array(hi, np.float32).reshape(shape),
                      dtype=np.float32)


def _model_file(path: str | Path) -> Path:
    p = Path(path)
    if p.is_dir():
        p = p / MODEL_FILE
    if not p.is_file():
        raise FileNotFoundError(f"policy file {p} does not exist; expected an SB3 model.zip or its run folder")
    return p


def _training_config_of(p: Path) -> TrainingConfig | None:
    """The ``training.yaml`` of a model file (beside it, or one up for ``checkpoints/``)."""
    for folder in (p.parent, p.parent.parent):
        f = folder / CONFIG_FILE
        if f.is_file():
            return load_config(f, model=TrainingConfig)
    return None


def _read_archive(p: Path) -> dict[str, Any]:
    """The ``data`` JSON of an SB3 archive, after checking it is one."""
    if not zipfile.is_zipfile(p):
        raise ValueError(f"{p} is not a stable-baselines3 model: not a zip file")
    try:
        with zipfile.ZipFile(p) as z:
            names = set(z.namelist())
            missing = [m for m in SB3_MEMBERS if m not in names]
            if missing:
                raise ValueError(
                    f"{p} is not a stable-baselines3 model: the zip lacks {', '.join(missing)}"
                )
            data = json.loads(z.read("data").decode())
    except (zipfile.BadZipFile, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p} is not a stable-baselines3 model: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{p} is not a stable-baselines3 model: 'data' is not a JSON object")
    return data


def _detect_algo(data: dict[str, Any], p: Path) -> str:
    module = str((data.get("policy_class") or {}).get("__module__", "")) if isinstance(
        data.get("policy_class"), dict) else ""
    if "sac" in module or ("tau" in data and "ent_coef" in data and "replay_buffer_class" in data):
        return "sac"
    if "clip_range" in data and "n_epochs" in data:
        return "ppo"
    raise ValueError(f"{p} is an SB3 model of an algorithm evaluate does not know; expected PPO or SAC")


def _safe_custom_objects(
    data: dict[str, Any], algo: str, train_cfg: TrainingConfig | None, p: Path
) -> dict[str, Any]:
    """Replacements for every pickled field of the archive (so that none is unpickled)."""
    from stable_baselines3.common.buffers import ReplayBuffer, RolloutBuffer
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
    from stable_baselines3.sac.policies import SACPolicy

    const = lambda _progress: 0.0
    known: dict[str, Any] = {
        "policy_class": SACPolicy if algo == "sac" else ActorCriticPolicy,
        "observation_space": None, "action_space": None,
        "lr_schedule": const, "clip_range": const, "clip_range_vf": None,
        "rollout_buffer_class": RolloutBuffer, "replay_buffer_class": ReplayBuffer,
        "train_freq": TrainFreq(1, TrainFrequencyUnit.STEP), "action_noise": None,
        "_last_obs": None, "_last_episode_starts": None, "_last_original_obs": None,
        "ep_info_buffer": None, "ep_success_buffer": None, "env": None,
        "buffer_size": 1,  # no replay memory is needed to act
    }
    pk = data.get("policy_kwargs")
    if train_cfg is not None and isinstance(pk, dict) and ":serialized:" in pk:
        # Pickled because of the activation class: rebuilt from training.yaml instead.
        known["policy_kwargs"] = {
            **({"use_sde": False} if algo == "sac" else {}), **_policy_kwargs(train_cfg)
        }
    for key, item in data.items():
        if key not in known and isinstance(item, dict) and ":serialized:" in item:
            raise ValueError(
                f"{p}: field {key!r} is a pickled object that evaluate will not unpickle; "
                "expected a model written by tridar-env train"
            )
    known["observation_space"] = _parse_box(data.get("observation_space"), "observation space", p)
    known["action_space"] = _parse_box(data.get("action_space"), "action space", p)
    return {key: known[key] for key in data if key in known}


class SB3Policy:
    """A saved SB3 policy as ``obs -> action``: VecNormalize statistics, then deterministic
    ``predict``. Observations must have the shape the policy was trained on.

    Attributes:
        model: the SB3 algorithm; ``algo``: ``ppo`` | ``sac``; ``path``: the model file.
    """

    def __init__(self, model: Any, algo: str, path: Path, stats: dict[str, np.ndarray] | None) -> None:
        self.model = model
        self.algo = algo
        self.path = path
        self.obs_shape = tuple(model.observation_space.shape)
        self.action_shape = tuple(model.action_space.shape)
        self._norm = None
        if stats is not None and bool(stats["norm_obs"]):
            self._norm = (
                stats["obs_mean"].astype(np.float64),
                np.sqrt(stats["obs_var"].astype(np.float64) + float(stats["epsilon"])),
                float(stats["clip_obs"]),
            )

    def reset(self) -> None:
        """Stateless (MLP policy)."""

    def normalize(self, obs: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """What VecNormalize fed the network during training."""
        o = np.asarray(obs, dtype=np.float64)
        if o.shape != self.obs_shape:
            raise ValueError(
                f"observation has shape {o.shape}; the policy {self.path} expects {self.obs_shape}"
            )
        if self._norm is not None:
            mean, std, clip = self._norm
            o = np.clip((o - mean) / std, -clip, clip)
        return o.astype(np.float32)

    def __call__(self, obs: npt.ArrayLike) -> npt.NDArray[np.float32]:
        action, _ = self.model.predict(self.normalize(obs), deterministic=True)
        return np.asarray(action, dtype=np.float32)


def load_policy(
    path: str | Path, *, cfg: MissionConfig | None = None, algo: str | None = None
) -> SB3Policy:
    """Load a policy written by :func:`train` (``model.zip`` or its run folder).

    The archive is checked (a zip with SB3's members, a PPO or SAC model, Box spaces) before SB3
    reads it, with replacements for every pickled field, so that nothing is unpickled.
    ``vecnormalize.npz`` next to the model is applied when present.

    Args:
        path: ``model.zip`` or the run folder holding it.
        cfg: mission config of the env the policy will fly: its action size is checked.
        algo: ``ppo`` | ``sac``; default: ``training.yaml`` beside the model, else detected.

    Raises:
        FileNotFoundError: no such file. ValueError: not an SB3 PPO/SAC model, or it does not fit
            the env; one line naming the file and what was expected.
    """
    p = _model_file(path)
    data = _read_archive(p)
    try:
        train_cfg = _training_config_of(p)
    except ConfigError:
        train_cfg = None  # not ours to read: fall back on what the archive says
    algo = algo or (train_cfg.algo if train_cfg is not None else _detect_algo(data, p))
    if algo not in ("ppo", "sac"):
        raise ValueError(f"algo={algo!r}; expected 'ppo' or 'sac'")
    custom = _safe_custom_objects(data, algo, train_cfg, p)
    try:
        model = _algo_class(algo).load(p, custom_objects=custom, device="cpu")
    except (RuntimeError, KeyError, ValueError, TypeError, AssertionError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{p}: cannot load this {algo.upper()} model ({reason})") from None
    stats_path = p.parent / (STATS_FILE if p.name == MODEL_FILE else f"{p.stem}_{STATS_FILE}")
    if not stats_path.is_file() and p.stem.startswith("model_") and p.stem.endswith("_steps"):
        stats_path = p.parent / f"vecnormalize_{p.stem[len('model_'):]}.npz"  # a checkpoint
    stats = _load_stats(stats_path) if stats_path.is_file() else None
    policy = SB3Policy(model, algo, p, stats)
    if stats is not None and stats["obs_mean"].shape != policy.obs_shape:
        raise ValueError(
            f"{stats_path} holds statistics of shape {stats['obs_mean'].shape}; the policy expects "
            f"{policy.obs_shape}"
        )
    from tridar_env.env import OBS_DIM

    if policy.obs_shape != (OBS_DIM,):
        raise ValueError(
            f"{p} expects observations of shape {policy.obs_shape}; DockingEnv gives ({OBS_DIM},)"
        )
    if cfg is not None:
        n_act = 6 if cfg.dynamics.chaser.attitude == "controlled" else 3
        if policy.action_shape != (n_act,):
            raise ValueError(
                f"{p} outputs actions of shape {policy.action_shape}; mission {cfg.name!r} "
                f"expects ({n_act},)"
            )
    return policy


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------
def evaluate(
    model: str | Path,
    *,
    env_id: str | None = None,
    perception: str = "tridar",
    episodes: int = 20,
    seed: int = 0,
    config: dict[str, Any] | None = None,
    max_steps: int | None = None,
    progress: bool = True,
    on_episode: Callable[[dict[str, Any]], None] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Fly a saved policy for ``episodes`` episodes (deterministic actions) and summarise.

    Episode ``i`` uses reset seed ``agents.campaign.env_seed(seed, i)``: the same as run ``i`` of a
    campaign with that seed and ``controller: sb3:<model>``, so both give the same rows.

    Args:
        model: ``model.zip`` or its run folder.
        env_id: default: the id the policy was trained on (from ``training.yaml``).
        perception: ``tridar`` (the intended test), ``truth+noise`` or ``truth``.
        episodes: number of episodes.
        seed: evaluation seed.
        config: mission-config overrides (default: those of the training run).
        max_steps: optional step cap per episode.
        progress: tqdm bar over episodes.
        on_episode: called with each row (in completion order when run in parallel).
        workers: run the episodes on a Dask LocalCluster with this many worker processes
            (None or 1: in this process); ``scheduler``: or on an existing Dask scheduler.

    Returns:
        ``(table, summary)``: a ``pandas.DataFrame`` (one row per episode, campaign columns) and
        :func:`agents.campaign.summarize` of it.
    """
    import pandas as pd

    from agents.campaign import (
        CampaignConfig,
        build_specs,
        iter_results,
        open_client,
        summarize,
        validate_campaign,
    )

    if episodes < 1:
        raise ValueError(f"episodes={episodes}; expected >= 1")
    p = _model_file(model)
    train_cfg = _training_config_of(p)
    env_id = env_id or (train_cfg.env_id if train_cfg else None)
    if env_id is None:
        raise ValueError(f"no env id given and no {CONFIG_FILE} beside {p}; pass --env-id")
    if config is None:
        config = dict(train_cfg.config) if train_cfg and _bare_id(train_cfg.env_id) == _bare_id(env_id) else {}
    camp = CampaignConfig(
        name="evaluate", env_id=env_id, perception=perception,  # type: ignore[arg-type]
        controller=f"sb3:{p.resolve()}", runs=episodes, seed=seed, max_steps=max_steps,
        config=config, mission=train_cfg.mission if train_cfg else None,
    )
    validate_campaign(camp, "evaluate")
    # Fail fast, with one line, on a bad file or a policy that does not fit the env.
    from agents.campaign import mission_config

    load_policy(p, cfg=mission_config(camp))
    rows = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=episodes, desc="evaluate", unit="ep")
    parallel = scheduler is not None or (workers is not None and workers > 1)
    try:
        with open_client(scheduler, workers) if parallel else contextlib.nullcontext() as client:
            for row in iter_results(build_specs(camp), client):
                if row["outcome"] == "error":
                    raise ValueError(f"episode {row['index']} failed: {row['cause']}")
                rows.append(row)
                if on_episode is not None:
                    on_episode(row)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if len(rows) != episodes:
        raise ValueError(f"{episodes - len(rows)} of {episodes} episodes did not complete (a worker died)")
    table = pd.DataFrame(rows).sort_values("index", kind="stable").reset_index(drop=True)
    return table, summarize(table)
