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
resolved config), ``checkpoints/`` (model + statistics every ``checkpoint_every_steps``),
``learning_curve.csv`` / ``.png`` (how the training episodes ended, per rollout, against steps
and wall time: :mod:`agents.learning_curve`), with ``validation:`` also ``validation.csv`` and
the best validated policy ``best_model.zip`` + ``best_model_vecnormalize.npz``
(:mod:`agents.validation`), and ``tb/`` (TensorBoard logs). The folder carries
the marker of :mod:`agents.outputs`: ``--force`` replaces those files only, and only in a folder
``train`` created.

Module map: the recipe (:mod:`agents.training_config`), the behaviour-cloning warm start
(:mod:`agents.pretrain`), safe loading of a saved policy (:mod:`agents.policies`: the archive is
checked and no pickled field of it is unpickled) and evaluation (:mod:`agents.evaluation`). This
module validates a training config and runs SB3's training loop; the names of the others are
importable from here too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import inspect
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.campaign_spec import check_run_identity
from agents.evaluation import evaluate
from agents.outputs import atomic_write, check_folder, claim_folder, lock_folder
from agents.policies import SB3Policy, load_policy, save_stats
from agents.pretrain import Demonstrations, collect_demonstrations, dagger, freeze_obs_stats, pretrain_policy
from agents.training_config import (
    CHECKPOINT_DIR,
    CONFIG_FILE,
    CURVE_FILE,
    CURVE_PLOT,
    MODEL_FILE,
    PRETRAIN_FILE,
    STATS_FILE,
    NormalizeConfig,
    PretrainConfig,
    TrainingConfig,
    ValidationConfig,
    algo_class,
    env_args,
    mission_path,
    policy_kwargs,
)
from perception.config import ConfigError, MissionConfig, config_path, load_config, save_config

__all__ = [
    "Demonstrations",
    "NormalizeConfig",
    "PretrainConfig",
    "SB3Policy",
    "TrainResult",
    "TrainingConfig",
    "ValidationConfig",
    "batch_refusal",
    "build_model",
    "collect_demonstrations",
    "evaluate",
    "load_policy",
    "load_training",
    "make_training_env",
    "pretrain_policy",
    "train",
    "validate_training",
    "vec_env_kind",
]

#: Marker kind of a training run folder (:mod:`agents.outputs`).
KIND = "train"
_CHECKPOINT_RE = re.compile(r"^(model|vecnormalize)_\d+_steps\.(zip|npz)$")

# Keyword arguments the trainer sets itself (not allowed in ``hyperparams``).
_RESERVED = {"policy", "env", "seed", "verbose", "tensorboard_log", "policy_kwargs", "device",
             "_init_setup_model"}


def validate_training(cfg: TrainingConfig, source: str = "training config") -> MissionConfig:
    """Check the id, the mission overrides and the hyperparameters; return the mission config.

    Raises:
        ConfigError: naming the field and the value.
    """
    def fail(msg: str) -> None:
        raise ConfigError(f"{source}: {msg}")

    check_run_identity(cfg.name, cfg.env_id, fail)
    if cfg.pretrain is not None and cfg.algo != "ppo":
        fail(f"pretrain is set with algo={cfg.algo!r}; behaviour cloning is implemented for 'ppo'")
    if cfg.mission is not None and not Path(cfg.mission).is_file():
        fail(f"mission={cfg.mission!r}: no such file")
    params = set(inspect.signature(algo_class(cfg.algo).__init__).parameters) - _RESERVED - {"self"}
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
            mission_path(cfg.env_id, cfg.mission), **cfg.config, **cfg.train_config,
            env__perception=cfg.perception
        )
    except ConfigError as exc:
        detail = "; ".join(line.strip() for line in str(exc).splitlines()[1:]) or str(exc)
        fail(f"config gives an invalid mission: {detail}")
    if cfg.vec_env == "batched":
        refusal = batch_refusal(mission)
        if refusal is not None:
            fail(f"vec_env='batched' but {refusal.split(' (use gymnasium')[0]}; expected vec_env "
                 "'auto', 'subproc' or 'dummy' for this run")
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
# Training
# ---------------------------------------------------------------------------------------------
@dataclass
class TrainResult:
    """Where a training run went.

    Attributes:
        out_dir: run folder; ``model_path``, ``stats_path``: the saved policy and statistics.
        timesteps: steps trained; ``wall_time_s``: time spent; ``interrupted``: Ctrl-C.
        vec_env: the vector env it ran on (``batched``, ``subproc`` or ``dummy``).
    """

    out_dir: Path
    model_path: Path
    stats_path: Path | None
    timesteps: int
    wall_time_s: float
    interrupted: bool = False
    vec_env: str = ""


def batch_refusal(mission: MissionConfig) -> str | None:
    """Why the training env of ``mission`` cannot be batched (None: it can).

    The batched adapter replaces ``gymnasium.make(id)`` (the env in its ``TimeLimit``, no other
    wrapper) by ``TruthVectorEnv``; that covers truth and truth+noise perception, CW dynamics and
    the ideal chaser attitude law, and its constructor names whatever else it does not batch.
    """
    from tridar_env.vector import TruthVectorEnv

    try:
        TruthVectorEnv(1, config=mission).close()
    except ValueError as exc:
        return str(exc)
    return None


def vec_env_kind(cfg: TrainingConfig, mission: MissionConfig) -> str:
    """The vector env a run uses: ``cfg.vec_env``, with ``auto`` resolved (``batched`` where
    :func:`batch_refusal` allows it, else ``subproc``; ``dummy`` for one env)."""
    if cfg.vec_env == "auto":
        if batch_refusal(mission) is None:
            return "batched"
        return "subproc" if cfg.n_envs > 1 else "dummy"
    return "dummy" if cfg.vec_env == "subproc" and cfg.n_envs == 1 else cfg.vec_env


def _make_vec_env(cfg: TrainingConfig, mission: MissionConfig, kind: str) -> Any:
    """SB3's vector env of the run (``kind`` from :func:`vec_env_kind`), seeded ``cfg.seed + k``."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    env_id, kwargs = env_args(cfg, mission)
    if kind == "batched":
        from agents.vec_adapter import make_batched_vec_env

        return make_batched_vec_env(env_id, cfg.n_envs, seed=cfg.seed, env_kwargs=kwargs)
    vec_cls = SubprocVecEnv if kind == "subproc" else DummyVecEnv
    return make_vec_env(env_id, n_envs=cfg.n_envs, seed=cfg.seed, vec_env_cls=vec_cls,
                        env_kwargs=kwargs)


def make_training_env(cfg: TrainingConfig, mission: MissionConfig) -> tuple[Any, str]:
    """The run's vector env (not yet normalised; only ``cfg.observation_blocks`` of the
    observation when given) and its kind (:func:`vec_env_kind`)."""
    kind = vec_env_kind(cfg, mission)
    venv = _make_vec_env(cfg, mission, kind)
    if cfg.observation_blocks is not None:
        from agents.observation_blocks import VecSelectObservation

        venv = VecSelectObservation(venv, cfg.observation_blocks)
    return venv, kind


def build_model(cfg: TrainingConfig, venv: Any, tensorboard_log: str | None = None) -> tuple[Any, Any]:
    """``(VecNormalize over venv, the untrained SB3 model on it)`` as ``cfg`` describes them."""
    from stable_baselines3.common.vec_env import VecNormalize

    gamma = float(cfg.hyperparams.get("gamma", 0.99))
    vec = VecNormalize(
        venv, norm_obs=cfg.normalize.obs, norm_reward=cfg.normalize.reward,
        clip_obs=cfg.normalize.clip_obs, clip_reward=cfg.normalize.clip_reward, gamma=gamma,
    )
    model = algo_class(cfg.algo)(
        "MlpPolicy", vec, seed=cfg.seed, verbose=0, tensorboard_log=tensorboard_log,
        policy_kwargs=policy_kwargs(cfg) or None, device=cfg.device, **cfg.hyperparams,
    )
    return vec, model


def _progress_bar_available() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("tqdm", "rich"))


def _checkpoint_callback(save_freq: int, path: Path, vec: Any) -> Any:
    from stable_baselines3.common.callbacks import CheckpointCallback

    class Checkpoint(CheckpointCallback):
        """SB3's checkpoint plus the normalisation statistics as ``.npz`` (no pickle)."""

        def _on_step(self) -> bool:
            if self.n_calls % self.save_freq == 0:
                save_stats(vec, Path(self.save_path) / f"vecnormalize_{self.num_timesteps}_steps.npz")
            return super()._on_step()

    return Checkpoint(save_freq=save_freq, save_path=str(path), name_prefix="model")


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


def _validation_callback(cfg: TrainingConfig, mission: MissionConfig, out: Path, vec: Any) -> Any:
    """The :class:`agents.validation.Validation` of ``cfg.validation`` (its env built here)."""
    import gymnasium as gym

    from agents.validation import Validation

    val = cfg.validation
    assert val is not None
    env_id, kwargs = env_args(cfg, mission, train=False)
    indices = None
    if cfg.observation_blocks is not None:
        from agents.observation_blocks import block_indices

        indices = block_indices(cfg.observation_blocks)

    def save(model: Any, vec: Any, model_path: Path, stats_path: Path) -> None:
        _save_model(model, model_path)
        save_stats(vec, stats_path)

    return Validation(gym.make(env_id, **kwargs), vec, out, val.every_steps, val.episodes, val.seed,
                      indices, save, at_start=val.at_start)


def _save_model(model: Any, path: Path) -> None:
    # Transient training state is left out: it is pickled by SB3 and useless for inference.
    exclude = ["_last_obs", "_last_episode_starts", "_last_original_obs", "ep_info_buffer",
               "ep_success_buffer", "env"]
    atomic_write(path, lambda tmp: model.save(tmp, exclude=exclude), suffix=".zip")


def _discard(out: Path) -> None:
    """``--force``: delete what an earlier ``train`` wrote in ``out`` (known names only; the
    TensorBoard logs stay, SB3 numbers the next run)."""
    from agents.validation import BEST_MODEL_FILE, BEST_STATS_FILE, VALIDATION_FILE

    for name in (MODEL_FILE, STATS_FILE, CONFIG_FILE, PRETRAIN_FILE, CURVE_FILE, CURVE_PLOT,
                 BEST_MODEL_FILE, BEST_STATS_FILE, VALIDATION_FILE):
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

    mission = validate_training(cfg)
    out = Path(out_dir)
    check_folder(out, KIND, destroy="--force" if force else None)
    if (out / MODEL_FILE).exists() and not force:
        raise ValueError(f"{out / MODEL_FILE} exists; pass --force to replace it or choose another --out")
    torch.set_num_threads(cfg.torch_threads)
    venv, kind = make_training_env(cfg, mission)
    with contextlib.ExitStack() as stack:
        stack.callback(venv.close)
        gamma = float(cfg.hyperparams.get("gamma", 0.99))
        tb = str(out / "tb") if importlib.util.find_spec("tensorboard") is not None else None
        vec, model = build_model(cfg, venv, tensorboard_log=tb)
        pretrain_stats = None
        if cfg.pretrain is not None:
            demos = collect_demonstrations(cfg, mission, progress=progress)
            indices = None
            if cfg.observation_blocks is not None:  # the controller saw it all, the policy will not
                from agents.observation_blocks import block_indices

                indices = block_indices(cfg.observation_blocks)
                demos = dataclasses.replace(demos, obs=demos.obs[:, indices])
            pretrain_stats = pretrain_policy(model, vec, demos, cfg.pretrain, gamma, cfg.seed)
            if cfg.pretrain.dagger_rounds:
                pretrain_stats["dagger"] = dagger(model, vec, demos, cfg, mission, indices, progress)
            if cfg.pretrain.freeze_obs_stats:
                freeze_obs_stats(vec)
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
        from agents.learning_curve import LearningCurve, plot_learning_curve

        callbacks = [LearningCurve(out / CURVE_FILE)]
        if cfg.validation is not None:
            callbacks.append(_validation_callback(cfg, mission, out, vec))
            stack.callback(callbacks[-1].env.close)
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
        save_stats(vec, out / STATS_FILE)
        if (out / CURVE_FILE).exists():
            from agents.validation import VALIDATION_FILE

            val = out / VALIDATION_FILE if (out / VALIDATION_FILE).exists() else None
            atomic_write(out / CURVE_PLOT,
                         lambda p: plot_learning_curve(out / CURVE_FILE, p, cfg.name, val), suffix=".png")
        return TrainResult(out, out / MODEL_FILE, out / STATS_FILE, int(model.num_timesteps), wall,
                           interrupted, kind)
