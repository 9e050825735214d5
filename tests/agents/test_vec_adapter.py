"""BatchedVecEnv: SB3's vector env over TruthVectorEnv, against single envs episode by episode."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import VecMonitor

import tridar_env  # noqa: F401  (registers the ids)
from agents.vec_adapter import BatchedVecEnv, make_batched_vec_env
from tests.agents.test_training import TINY as TRAINING_TINY
from tridar_env.env import OBS_DIM
from tridar_env.vector import TruthVectorEnv

N = 4
SEED = 7
# Short episodes from 2-4 m: thrust towards the port ends them in contact, sideways in a corridor
# exit, and otherwise the time limit truncates them.
CLOSE = {
    "env__initial__range_m": 3.0,
    "env__initial__range_dispersion_m": 1.0,
    "env__initial__range_min_m": 2.0,
    "max_episode_steps": 80,
}
TOWARDS_PORT = np.array([0.8, 0.8, 0.0, -0.3])  # per env, added to the +z (boresight) action


def _single_env_episodes(env_id: str, kw: dict, actions: np.ndarray) -> list[list[tuple]]:
    """Env ``i`` (``gym.make``) flies ``actions[:, i]``: reset with ``SEED + i``, then without a
    seed after every episode (SB3's order). Per env, per step: (obs after the step, the next
    episode's first obs or None, reward, terminated, truncated, cause)."""
    out = []
    for i in range(N):
        env = gym.make(env_id, **kw)
        obs, _ = env.reset(seed=SEED + i)
        rows = [(obs, None, 0.0, False, False, "")]
        for a in actions[:, i]:
            obs, r, term, trunc, info = env.step(a)
            first = env.reset()[0] if term or trunc else None
            rows.append((obs, first, r, term, trunc, info["termination"]))
        env.close()
        out.append(rows)
    return out


@pytest.mark.parametrize(
    ("env_id", "kw", "steps", "n_outcomes"),
    [
        ("TriDAR/FinalApproach-v0", {"perception": "truth+noise", **CLOSE}, 400, 3),
        ("TriDAR/FinalApproach-v0", {"perception": "truth", **CLOSE}, 250, 2),
        # A spinning target (its attitude integrated per environment), truncated far out.
        (
            "TriDAR/TumblingTarget-v0",
            {
                "perception": "truth+noise",
                "dynamics__chaser__attitude": "ideal",
                "max_episode_steps": 60,
            },
            200,
            1,
        ),
    ],
)
def test_episodes_equal_the_single_envs_seed_for_seed(
    env_id: str, kw: dict, steps: int, n_outcomes: int
) -> None:
    """Same seeds, same actions: every episode of every environment ends at the same step, the
    same way, with the same final observation (``terminal_observation``), and the next one starts
    from the same first observation (same-step autoreset), for several episodes per environment.

    Observations, rewards, terminations, truncations and causes are identical, bit for bit:
    ``TruthVectorEnv`` performs the single env's floating-point operations in its order (the noise
    is 1e-2 to 1e-4 of the observations: a stream one draw off fails too)."""
    rng = np.random.default_rng(0)
    actions = 0.3 * rng.uniform(-1.0, 1.0, (steps, N, 3))
    actions[:, :, 2] += TOWARDS_PORT
    actions = actions.astype(np.float32)
    ref = _single_env_episodes(env_id, kw, actions)
    venv = make_batched_vec_env(env_id, N, seed=SEED, env_kwargs=kw, monitor=False)
    obs = venv.reset()
    np.testing.assert_array_equal(obs, np.stack([ref[i][0][0] for i in range(N)]))
    episodes = np.zeros(N, dtype=int)
    for k in range(steps):
        venv.step_async(actions[k])
        obs, reward, done, infos = venv.step_wait()
        for i in range(N):
            last, first, r, term, trunc, cause = ref[i][k + 1]
            assert done[i] == (term or trunc), (k, i)
            np.testing.assert_array_equal(reward[i], r)
            if done[i]:
                episodes[i] += 1
                assert infos[i]["TimeLimit.truncated"] == (trunc and not term)
                assert infos[i]["termination"] == cause
                np.testing.assert_array_equal(infos[i]["terminal_observation"], last)
                np.testing.assert_array_equal(obs[i], first)
            else:
                assert (
                    "terminal_observation" not in infos[i] and not infos[i]["TimeLimit.truncated"]
                )
                np.testing.assert_array_equal(obs[i], last)
    assert episodes.min() >= 2, (
        episodes
    )  # several episodes each: the autoreset streams were checked
    outcomes = {row[5] or "truncated" for rows in ref for row in rows[1:] if row[3] or row[4]}
    assert len(outcomes) >= n_outcomes, outcomes
    venv.close()


def test_simultaneous_ends_are_bitwise_the_batched_env() -> None:
    """When every episode ends together, the adapter's same-step reset is ``TruthVectorEnv``'s
    next-step reset moved one step earlier: the same arithmetic, bit for bit."""
    kw = {"perception": "truth+noise", "max_episode_steps": 15}
    adapter = make_batched_vec_env(
        "TriDAR/FinalApproach-v0", N, seed=SEED, env_kwargs=kw, monitor=False
    )
    batched = gym.make_vec(
        "TriDAR/FinalApproach-v0", num_envs=N, vectorization_mode="vector_entry_point", **kw
    )
    o1 = adapter.reset()
    o2, _ = batched.reset(seed=SEED)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    for k in range(50):
        a = rng.uniform(-0.2, 0.2, (N, 3)).astype(np.float32)
        adapter.step_async(a)
        o1, r1, d1, i1 = adapter.step_wait()
        o2, r2, te, tr, _ = batched.step(a)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(d1, te | tr)
        if d1.any():
            assert d1.all() and not te.any()  # all truncated together
            np.testing.assert_array_equal(np.stack([i["terminal_observation"] for i in i1]), o2)
            o2, *_ = batched.step(a)  # the batched env's reset step (its action is ignored)
        np.testing.assert_array_equal(o1, o2)
    adapter.close()
    batched.close()


def test_sb3_protocol_seeds_infos_and_monitor() -> None:
    venv = make_batched_vec_env(
        "TriDAR/FinalApproach-v0",
        3,
        seed=0,
        env_kwargs={"perception": "truth", "max_episode_steps": 5},
    )
    assert isinstance(venv, VecMonitor) and isinstance(venv.venv, BatchedVecEnv)
    assert venv.get_attr("render_mode") == [None] * 3
    assert venv.env_is_wrapped(gym.Wrapper) == [False] * 3
    obs = venv.reset()
    assert obs.shape == (3, OBS_DIM) and obs.dtype == np.float32
    venv.seed(0)  # the same seeds again: the same first observations
    np.testing.assert_array_equal(venv.reset(), obs)
    for _ in range(5):
        venv.step_async(np.zeros((3, 3), dtype=np.float32))
        _, _, done, infos = venv.step_wait()
    assert done.all()
    for info in infos:
        assert info["episode"]["l"] == 5 and info["TimeLimit.truncated"]
        assert set(info) >= {
            "termination",
            "t",
            "delta_v",
            "reward_progress",
            "terminal_observation",
        }
    with pytest.raises(ValueError, match="env_method"):
        venv.env_method("reset")
    venv.close()


def test_unbatchable_configurations_are_refused_naming_the_field() -> None:
    with pytest.raises(ValueError, match="env.perception='tridar'"):
        make_batched_vec_env("TriDAR/FinalApproach-v0", 2, env_kwargs={"perception": "tridar"})
    with pytest.raises(ValueError, match="dynamics.chaser.attitude='controlled'"):
        make_batched_vec_env("TriDAR/TumblingTarget-v0", 2, env_kwargs={"perception": "truth"})
    assert issubclass(
        type(
            make_batched_vec_env(
                "TriDAR/FinalApproach-v0", 1, env_kwargs={"perception": "truth"}, monitor=False
            ).venv
        ),
        TruthVectorEnv,
    )


# ------------------------------------------------------------------------------------------- train
# The training tests' tiny run, with 4 envs and the default vec_env (auto).
TINY = {k: v for k, v in {**TRAINING_TINY, "n_envs": 4}.items() if k != "vec_env"}


def test_train_uses_the_adapter_where_the_run_allows_it(tmp_path) -> None:
    from agents.training import TrainingConfig, train, validate_training, vec_env_kind

    cfg = TrainingConfig(**TINY)
    assert cfg.vec_env == "auto"
    res = train(cfg, tmp_path / "run", progress=False)
    assert res.vec_env == "batched" and res.timesteps >= 256 and res.model_path.is_file()
    for perception, n_envs, kind in (
        ("truth", 4, "batched"),
        ("tridar", 4, "subproc"),
        ("tridar", 1, "dummy"),
    ):
        c = TrainingConfig(**{**TINY, "perception": perception, "n_envs": n_envs})
        assert vec_env_kind(c, validate_training(c)) == kind
    # 6-DOF actions need the controlled attitude, which the batched env does not fly.
    c = TrainingConfig(**{**TINY, "env_id": "TriDAR/TumblingTarget-v0"})
    assert vec_env_kind(c, validate_training(c)) == "subproc"
    c = TrainingConfig(**{**TINY, "vec_env": "subproc"})
    assert vec_env_kind(c, validate_training(c)) == "subproc"


def test_batched_on_a_run_it_cannot_batch_is_one_clear_error() -> None:
    from agents.training import TrainingConfig, validate_training
    from perception.config import ConfigError

    cfg = TrainingConfig(**{**TINY, "vec_env": "batched", "perception": "tridar"})
    with pytest.raises(
        ConfigError,
        match=r"vec_env='batched' but .*env.perception='tridar'.*expected vec_env 'auto'",
    ):
        validate_training(cfg)


def test_bench_train_prints_steps_per_second_and_the_ratio(tmp_path, capsys) -> None:
    import yaml

    from agents.cli import main

    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({**TINY, "n_envs": 2}))
    code = main(
        [
            "bench",
            "train",
            "--config",
            str(path),
            "--steps",
            "64",
            "--repeats",
            "1",
            "--vec-envs",
            "dummy",
            "batched",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "steps_per_s_median" in out and "steps_per_s_p90" in out and "ratio_to_dummy" in out
    assert "| batched" in out and "goal: batched >= 3x" in out
