"""``BatchedVecEnv``: stable-baselines3's ``VecEnv`` over the batched truth environments.

SB3 steps its environments through a ``VecEnv``; with ``SubprocVecEnv`` every step of every
environment is a message to another process, and for the truth stand-ins (``perception="truth"``
and ``"truth+noise"``) that messaging costs far more than the step. This adapter drives one
:class:`~tridar_env.vector.TruthVectorEnv`, which steps all the environments as arrays, and speaks
SB3's protocol:

- ``step_wait`` returns ``(obs, rewards, dones, infos)`` with ``dones = terminated | truncated``;
- a finished environment is reset in the same step (SB3's autoreset): its slot of ``obs`` is the
  first observation of its next episode, ``infos[i]["terminal_observation"]`` the last one of the
  episode that ended, and ``infos[i]["TimeLimit.truncated"]`` says the time limit ended it (PPO
  then bootstraps its value);
- ``seed(s)`` gives environment ``i`` the seed ``s + i`` at the next ``reset()``, as SB3's own
  vector envs; later episodes continue each environment's generator, as a single env's would.

So environment ``i`` flies, seed for seed and action for action, the episodes of
``gymnasium.make(id, **kwargs)`` reset with ``seed + i`` and then reset without a seed whenever an
episode ends (``DummyVecEnv``'s sequence). Observations (terminal ones included), rewards, episode
lengths, terminations, truncations and causes are identical, bit for bit (``TruthVectorEnv``
performs the single env's floating-point operations in its order);
``tests/agents/test_vec_adapter.py`` holds the two together.

The per-environment ``infos`` carry what ``TruthVectorEnv`` reports (``termination``, ``t``,
``delta_v``, the ``reward_*`` terms, ...), not the single env's pipeline fields. Wrap the adapter in
``VecMonitor`` for SB3's ``episode`` statistics (:func:`make_batched_vec_env` does).

    >>> from agents.vec_adapter import make_batched_vec_env
    >>> venv = make_batched_vec_env("TriDAR/FinalApproach-v0", 8, seed=0,
    ...                             env_kwargs={"perception": "truth+noise"})
    >>> venv.reset().shape
    (8, 36)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from tridar_env.vector import TruthVectorEnv

__all__ = ["BatchedVecEnv", "SameStepTruthVectorEnv", "make_batched_vec_env"]


class SameStepTruthVectorEnv(TruthVectorEnv):
    """``TruthVectorEnv`` that can also reset a subset of its environments now
    (:meth:`reset_done`), which SB3's same-step autoreset needs.

    The initial states are drawn by ``TruthVectorEnv``'s own reset, and the first observations by
    its own observation, with only the reset environments' generators drawing noise: each
    environment's random stream is the one its single env would consume.
    """

    _only: npt.NDArray[np.intp] | None = None

    def reset_done(self, idx: npt.NDArray[np.intp]) -> npt.NDArray[np.float32]:
        """Start the next episode of environments ``idx`` (which have just ended) without a seed;
        return their first observations, ``(len(idx), obs_dim)``."""
        first = np.zeros(self.num_envs, dtype=bool)
        first[idx] = True
        self._reset_envs(idx)
        self._autoreset[idx] = False  # reset here, not by the next step()
        self._only = idx
        try:
            obs = self._observe(first=first)
        finally:
            self._only = None
        return obs[idx]

    def _draws(self, first: npt.NDArray[np.bool_]) -> tuple[Any, Any]:
        """``TruthVectorEnv._draws`` of environments ``_only`` alone (all when None): the noise
        state is narrowed to them for the call, so the others' generators do not draw."""
        idx = self._only
        if idx is None:
            return super()._draws(first)
        full = (self._rngs, self._err, self._t, self._t_err, self.num_envs)
        self._rngs = [full[0][i] for i in idx.tolist()]
        self._err, self._t, self._t_err = full[1][idx], full[2][idx], full[3][idx]
        self.num_envs = idx.size
        try:
            err, gyro = super()._draws(first[idx])
            full[1][idx] = err
            full[3][idx] = self._t_err
        finally:
            self._rngs, self._err, self._t, self._t_err, self.num_envs = full
        gyro_all = np.zeros((self.num_envs, 3))
        gyro_all[idx] = gyro
        return self._err, gyro_all


def _split_info(info: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """``TruthVectorEnv``'s info of arrays as ``n`` per-environment dicts (scalars as Python
    numbers, vectors as rows)."""
    cols = {k: (v.tolist() if v.ndim == 1 else list(v)) for k, v in info.items()}
    return [{k: c[i] for k, c in cols.items()} for i in range(n)]


class BatchedVecEnv(VecEnv):
    """SB3 ``VecEnv`` over one :class:`SameStepTruthVectorEnv` (see the module docstring).

    Args:
        venv: the batched environments (built by :func:`make_batched_vec_env`).
    """

    def __init__(self, venv: SameStepTruthVectorEnv) -> None:
        self.venv = venv
        self._actions: npt.NDArray[Any] | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    @property
    def cfg(self) -> Any:
        """The resolved mission config of the environments."""
        return self.venv.cfg

    def reset(self) -> npt.NDArray[np.float32]:
        if any(self._options):
            raise ValueError(f"reset options {self._options!r}; BatchedVecEnv takes none")
        obs, info = self.venv.reset(seed=list(self._seeds))
        self.reset_infos = _split_info(info, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(
        self,
    ) -> tuple[
        npt.NDArray[np.float32],
        npt.NDArray[np.float64],
        npt.NDArray[np.bool_],
        list[dict[str, Any]],
    ]:
        if self._actions is None:
            raise RuntimeError("BatchedVecEnv.step_wait() without step_async(actions)")
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        self._actions = None
        dones = terminated | truncated
        infos = _split_info(info, self.num_envs)
        if dones.any():
            idx = np.flatnonzero(dones)
            for i in idx.tolist():
                infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                infos[i]["terminal_observation"] = obs[i].copy()
                self.reset_infos[i] = {}
            obs[idx] = self.venv.reset_done(idx)
        for i in np.flatnonzero(~dones).tolist():
            infos[i]["TimeLimit.truncated"] = False
        return obs, reward, dones, infos

    def close(self) -> None:
        self.venv.close()

    # Per-environment access. The environments are rows of one object: attributes are shared,
    # there are no per-environment methods and no wrappers.
    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.venv, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        if len(list(self._get_indices(indices))) != self.num_envs:
            raise ValueError(
                f"set_attr({attr_name!r}) on indices {indices!r}; the batched environments share "
                "their attributes: expected indices=None (all)"
            )
        setattr(self.venv, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        raise ValueError(
            f"env_method({method_name!r}): the batched environments have no per-environment "
            "methods; use vec_env 'subproc' or 'dummy' for that"
        )

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None] * self.num_envs


def make_batched_vec_env(
    env_id: str,
    n_envs: int,
    *,
    seed: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
    monitor: bool = True,
) -> VecEnv:
    """SB3's vector env for ``n_envs`` copies of ``gymnasium.make(env_id, **env_kwargs)``, batched.

    Args:
        env_id: a registered id (``TriDAR/FinalApproach-v0``, optionally ``tridar_env:``-prefixed).
        n_envs: environments.
        seed: environment ``i`` is reset with ``seed + i`` first (None: fresh entropy).
        env_kwargs: ``gymnasium.make`` keyword arguments (``perception``, ``config``,
            ``max_episode_steps``, ``__``-nested overrides).
        monitor: wrap in ``VecMonitor`` (episode returns and lengths in ``infos[i]["episode"]``).

    Raises:
        ValueError: a configuration ``TruthVectorEnv`` does not batch (the message names the
            field and the value), or an id without a batched entry point.
    """
    import gymnasium as gym

    import tridar_env  # noqa: F401  (registers the ids)
    from tridar_env.registration import bare_id

    spec = gym.spec(bare_id(env_id))
    if spec.vector_entry_point != "tridar_env.vector:TruthVectorEnv":
        raise ValueError(
            f"env_id={env_id!r} has no batched truth entry point; expected a TriDAR id"
        )
    venv = BatchedVecEnv(SameStepTruthVectorEnv(n_envs, **{**spec.kwargs, **(env_kwargs or {})}))
    if seed is not None:  # SB3's seed(None) would draw from the global numpy state
        venv.seed(seed)
    return VecMonitor(venv) if monitor else venv
