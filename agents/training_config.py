"""The training recipe: the models of a training YAML and the pure helpers derived from them.

:class:`TrainingConfig` (with :class:`NormalizeConfig` and :class:`PretrainConfig`) is what
``configs/training/*.yaml`` hold; the file names of a run folder are here too, so that the trainer
(:mod:`agents.training`) that writes them and the loader (:mod:`agents.policies`) that reads them
agree. Checking a config against the env and the controllers is :func:`agents.training.validate_training`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from perception.config import MissionConfig, config_path
from tridar_env.registration import bare_id

__all__ = [
    "CHECKPOINT_DIR",
    "CONFIG_FILE",
    "MODEL_FILE",
    "PRETRAIN_FILE",
    "STATS_FILE",
    "NormalizeConfig",
    "PretrainConfig",
    "TrainingConfig",
    "algo_class",
    "bare_id",
    "env_args",
    "mission_path",
    "policy_kwargs",
]

MODEL_FILE = "model.zip"
STATS_FILE = "vecnormalize.npz"
CONFIG_FILE = "training.yaml"
PRETRAIN_FILE = "pretrain.json"
CHECKPOINT_DIR = "checkpoints"
CURVE_FILE = "learning_curve.csv"
CURVE_PLOT = "learning_curve.png"


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

    With ``dagger_rounds`` > 0 the cloning goes on as DAgger (Ross, Gordon and Bagnell 2011): each
    round the cloned policy flies ``dagger_episodes`` episodes itself (its mean action, plus the
    same ``action_noise``) while the controller, run alongside on the same observations, labels
    every state it visits; the policy mean is fitted again, for ``dagger_epochs`` passes, to all
    the labelled states so far. Plain cloning learns only the controller's own states, and a
    policy that drifts a little from them meets states it never saw (``sync`` cloned from 100
    episodes at ``action_noise`` 0.05 to an action error of 6e-4 docked 5 of 30 tumbling runs).
    DAgger suits a controller whose action follows from what it observes; off its own path a
    stateful one's labels depend on phases and filters the policy does not see (on ``sync``,
    four rounds made it worse). A larger ``action_noise`` (DART: the controller itself shows how
    it recovers, its state consistent with its flight) is the other remedy:
    ``configs/training/bc_tumbling_target.yaml`` (300 episodes at 0.2: 30 of 30).

    ``freeze_obs_stats``: VecNormalize's observation statistics stay as the cloning left them
    while PPO trains (otherwise PPO's rollouts move them, and with them every input of the cloned
    actor, even while the critic warm-up keeps the actor itself frozen).
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
    dagger_rounds: Annotated[int, Field(ge=0, le=100)] = 0
    dagger_episodes: Annotated[int, Field(ge=1)] = 50
    dagger_epochs: Annotated[int, Field(ge=1)] = 10
    freeze_obs_stats: bool = False


class ValidationConfig(BaseModel):
    """Validation while training (:mod:`agents.validation`): every ``every_steps`` total steps
    the current policy flies ``episodes`` runs of the mission as evaluation flies it (reset seeds
    ``seed + k``); the best so far is kept as ``best_model.zip``. ``at_start``: the policy PPO
    starts from is validated too (at 0 steps): a warm start cloned from a controller may be the
    best policy of the run."""

    model_config = ConfigDict(extra="forbid")

    every_steps: Annotated[int, Field(ge=1)]
    episodes: Annotated[int, Field(ge=1, le=10_000)] = 50
    seed: Annotated[int, Field(ge=0)] = 1_000_000
    at_start: bool = False


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
        n_envs: parallel envs. ``vec_env``: ``batched`` steps them all as arrays in this process
            (:class:`agents.vec_adapter.BatchedVecEnv` over ``TruthVectorEnv``: truth and
            truth+noise perception, CW dynamics, the ideal chaser attitude law), ``subproc`` one
            process each, ``dummy`` one after the other in this process; ``auto`` is ``batched``
            where the run allows it and ``subproc`` (``dummy`` for one env) elsewhere.
        seed: seeds SB3, torch and the envs (env ``k`` gets ``seed + k``).
        normalize: VecNormalize settings.
        checkpoint_every_steps: save model + statistics every this many total steps (None: off).
        net_arch, activation, log_std_init: policy network.
        hyperparams: keyword arguments of the SB3 algorithm (``learning_rate``, ``n_steps``, ...).
        observation_blocks: the blocks of the observation the policy sees (names of
            :data:`tridar_env.env.OBSERVATION_STRUCTURE`, in this order; None: all of it). Leave
            out what the training perception cannot reproduce (:mod:`agents.observation_blocks`).
        validation: optional validation while training, the best policy kept
            (:class:`ValidationConfig`).
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
    vec_env: Literal["auto", "batched", "subproc", "dummy"] = "auto"
    seed: Annotated[int, Field(ge=0)] = 0
    normalize: NormalizeConfig = NormalizeConfig()
    checkpoint_every_steps: Annotated[int, Field(ge=1)] | None = 100_000
    net_arch: list[Annotated[int, Field(ge=1)]] | None = None
    activation: Literal["tanh", "relu", "elu", "leaky_relu"] | None = None
    log_std_init: float | None = None
    hyperparams: dict[str, Any] = Field(default_factory=dict)
    observation_blocks: list[str] | None = None
    validation: ValidationConfig | None = None
    pretrain: PretrainConfig | None = None
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    torch_threads: Annotated[int, Field(ge=1)] = 1


    @field_validator("observation_blocks")
    @classmethod
    def _blocks(cls, v: list[str] | None) -> list[str] | None:
        if v is None:
            return v
        from agents.observation_blocks import check_blocks

        return check_blocks(v)


def algo_class(algo: str) -> Any:
    """The SB3 class of ``algo`` (``ppo`` | ``sac``)."""
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def mission_path(env_id: str, mission: str | None) -> Path:
    """The mission YAML of a run: ``mission``, else the id's own file."""
    from tridar_env.registration import ENV_IDS

    return Path(mission) if mission else config_path(ENV_IDS[bare_id(env_id)])


def env_args(cfg: TrainingConfig, mission: MissionConfig, train: bool = True) -> tuple[str, dict[str, Any]]:
    """``(env id, gym.make keyword arguments)`` of the training env (``train_config`` included;
    with ``train=False`` without it: the mission as evaluation flies it)."""
    env_id = cfg.env_id if ":" in cfg.env_id else f"tridar_env:{cfg.env_id}"
    overrides = {**cfg.config, **cfg.train_config} if train else dict(cfg.config)
    kwargs = {
        "perception": cfg.perception, "config": cfg.mission,
        "max_episode_steps": mission.env.max_episode_steps,
        **{k: v for k, v in overrides.items() if k.replace(".", "__") != "env__perception"},
    }
    return env_id, kwargs


def policy_kwargs(cfg: TrainingConfig) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` of the network fields (net_arch, activation, log_std_init)."""
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
