"""Saved policies, loaded without unpickling: ``model.zip`` (+ ``vecnormalize.npz``) as ``obs -> action``.

:func:`load_policy` checks that the file is a zip with SB3's members and hands SB3 replacements for
every pickled field of the archive, so that no user-supplied bytes are unpickled; the network
weights are read by ``torch.load(weights_only=True)``. The ``VecNormalize`` statistics travel as
plain arrays (:func:`save_stats`, :func:`load_stats`) for the same reason. Controllers named
``sb3:<path>`` (:func:`agents.controllers.make_controller`) come from here.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from agents.outputs import atomic_write
from agents.training_config import (
    CONFIG_FILE,
    MODEL_FILE,
    STATS_FILE,
    TrainingConfig,
    algo_class,
    policy_kwargs,
)
from perception.config import ConfigError, MissionConfig, load_config

__all__ = [
    "SB3_MEMBERS",
    "SB3Policy",
    "load_policy",
    "load_stats",
    "model_file",
    "save_stats",
    "training_config_of",
]

#: Members every SB3 model archive has.
SB3_MEMBERS = ("data", "policy.pth")


# ---------------------------------------------------------------------------------------------
# VecNormalize statistics as plain arrays
# ---------------------------------------------------------------------------------------------
def save_stats(vec: Any, path: Path) -> None:
    """Write ``vec``'s statistics to ``path`` (``.npz``, atomically)."""
    arrays = {
        "obs_mean": vec.obs_rms.mean, "obs_var": vec.obs_rms.var, "obs_count": vec.obs_rms.count,
        "ret_mean": vec.ret_rms.mean, "ret_var": vec.ret_rms.var, "ret_count": vec.ret_rms.count,
        "clip_obs": vec.clip_obs, "clip_reward": vec.clip_reward, "epsilon": vec.epsilon,
        "gamma": vec.gamma, "norm_obs": vec.norm_obs, "norm_reward": vec.norm_reward,
    }
    # The temporary name ends in .npz: np.savez would append it otherwise.
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")


def load_stats(path: Path) -> dict[str, np.ndarray]:
    """Read statistics written by :func:`save_stats` (``allow_pickle=False``)."""
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


def model_file(path: str | Path) -> Path:
    """``path`` itself, or the ``model.zip`` in the run folder ``path``; FileNotFoundError if none."""
    p = Path(path)
    if p.is_dir():
        p = p / MODEL_FILE
    if not p.is_file():
        raise FileNotFoundError(f"policy file {p} does not exist; expected an SB3 model.zip or its run folder")
    return p


def training_config_of(p: Path) -> TrainingConfig | None:
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
        # A malformed file, not a caller's type error: ValueError like every other bad archive.
        raise ValueError(f"{p} is not a stable-baselines3 model: 'data' is not a JSON object")  # noqa: TRY004
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
            **({"use_sde": False} if algo == "sac" else {}), **policy_kwargs(train_cfg)
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
        model: the SB3 algorithm; ``algo``: ``ppo`` | ``sac``; ``path``: the model file;
        ``blocks``: the observation blocks its network sees (None: all), ``indices`` theirs.
    """

    def __init__(
        self, model: Any, algo: str, path: Path, stats: dict[str, np.ndarray] | None,
        blocks: list[str] | None = None,
    ) -> None:
        self.model = model
        self.algo = algo
        self.path = path
        self.blocks = blocks
        #: Indices of the blocks the network sees in the full observation (None: all of it).
        self.indices = None
        self.obs_shape = tuple(model.observation_space.shape)
        if blocks is not None:
            from agents.observation_blocks import block_indices
            from tridar_env.env import OBS_DIM

            self.indices = block_indices(blocks)
            self.obs_shape = (OBS_DIM,)
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
        """What VecNormalize fed the network during training (the blocks it saw, normalised)."""
        o = np.asarray(obs, dtype=np.float64)
        if o.shape != self.obs_shape:
            raise ValueError(
                f"observation has shape {o.shape}; the policy {self.path} expects {self.obs_shape}"
            )
        if self.indices is not None:
            o = o[self.indices]
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
    p = model_file(path)
    data = _read_archive(p)
    try:
        train_cfg = training_config_of(p)
    except ConfigError:
        train_cfg = None  # not ours to read: fall back on what the archive says
    algo = algo or (train_cfg.algo if train_cfg is not None else _detect_algo(data, p))
    if algo not in ("ppo", "sac"):
        raise ValueError(f"algo={algo!r}; expected 'ppo' or 'sac'")
    custom = _safe_custom_objects(data, algo, train_cfg, p)
    try:
        model = algo_class(algo).load(p, custom_objects=custom, device="cpu")
    except (RuntimeError, KeyError, ValueError, TypeError, AssertionError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{p}: cannot load this {algo.upper()} model ({reason})") from None
    stats_path = p.parent / (STATS_FILE if p.name == MODEL_FILE else f"{p.stem}_{STATS_FILE}")
    if not stats_path.is_file() and p.stem.startswith("model_") and p.stem.endswith("_steps"):
        stats_path = p.parent / f"vecnormalize_{p.stem[len('model_'):]}.npz"  # a checkpoint
    stats = load_stats(stats_path) if stats_path.is_file() else None
    blocks = train_cfg.observation_blocks if train_cfg is not None else None
    policy = SB3Policy(model, algo, p, stats, blocks)
    net_shape = tuple(model.observation_space.shape)
    if stats is not None and stats["obs_mean"].shape != net_shape:
        raise ValueError(
            f"{stats_path} holds statistics of shape {stats['obs_mean'].shape}; the policy expects "
            f"{net_shape}"
        )
    from tridar_env.env import OBS_DIM

    want = (OBS_DIM,) if policy.indices is None else (len(policy.indices),)
    if net_shape != want:
        seen = "DockingEnv gives" if blocks is None else "its training.yaml's observation_blocks give"
        raise ValueError(f"{p} expects observations of shape {net_shape}; {seen} {want}")
    if cfg is not None:
        n_act = 6 if cfg.dynamics.chaser.attitude == "controlled" else 3
        if policy.action_shape != (n_act,):
            raise ValueError(
                f"{p} outputs actions of shape {policy.action_shape}; mission {cfg.name!r} "
                f"expects ({n_act},)"
            )
    return policy
