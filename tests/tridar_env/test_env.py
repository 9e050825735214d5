"""DockingEnv: the Gymnasium contract, determinism, rewards, terminations, rendering, vector envs."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest

import tridar_env
from agents.glideslope import GlideslopeController, GlideslopeGains
from perception.config import ConfigError
from tridar_env.env import OBS_DIM, observation_slices

IDS = list(tridar_env.ENV_IDS)


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_and_sb3_checkers_pass_without_warnings(env_id: str) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, perception="truth", render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped, warn=True)
    assert env.observation_space.shape == (OBS_DIM,)
    assert env.observation_space.dtype == np.float32 and env.action_space.dtype == np.float32
    assert np.all(np.isfinite(env.observation_space.low)) and np.all(np.isfinite(env.observation_space.high))


def _rollout(env: gym.Env, seed: int, n: int, policy=None) -> list[tuple]:
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    out = [(obs.copy(), 0.0)]
    for _ in range(n):
        a = policy(obs) if policy else env.action_space.sample()
        obs, r, term, trunc, _ = env.step(a)
        out.append((obs.copy(), r))
        if term or trunc:
            break
    return out


@pytest.mark.parametrize("perception", ["truth", "truth+noise"])
def test_same_seed_identical_rollouts(perception: str) -> None:
    a = _rollout(gym.make("TriDAR/FinalApproach-v0", perception=perception), 7, 60)
    b = _rollout(gym.make("TriDAR/FinalApproach-v0", perception=perception), 7, 60)
    c = _rollout(gym.make("TriDAR/FinalApproach-v0", perception=perception), 8, 60)
    assert len(a) == len(b)
    for (oa, ra), (ob, rb) in zip(a, b):
        np.testing.assert_array_equal(oa, ob)
        assert ra == rb
    assert not np.array_equal(a[1][0], c[1][0])


def test_tumbling_rollouts_identical() -> None:
    a = _rollout(gym.make("TriDAR/TumblingTarget-v0", perception="truth+noise"), 3, 15)
    b = _rollout(gym.make("TriDAR/TumblingTarget-v0", perception="truth+noise"), 3, 15)
    for (oa, ra), (ob, rb) in zip(a, b):
        np.testing.assert_array_equal(oa, ob)
        assert ra == rb


def test_reward_terms_sum_to_reward() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    env.reset(seed=0)
    env.action_space.seed(0)
    names = set()
    for _ in range(50):
        _, r, term, _, info = env.step(env.action_space.sample())
        terms = {k: v for k, v in info.items() if k.startswith("reward_")}
        names |= set(terms)
        assert r == pytest.approx(sum(terms.values()), abs=1e-12)
        if term:
            break
    assert names == {
        "reward_progress", "reward_lateral", "reward_alignment", "reward_speed_limit",
        "reward_speed_profile", "reward_time", "reward_fuel", "reward_success", "reward_collision",
        "reward_corridor",
    }


def _fly(env_id: str, seed: int, gains: GlideslopeGains | None = None, **kw) -> dict:
    env = gym.make(env_id, perception="truth", **kw)
    obs, info = env.reset(seed=seed)
    ctl = GlideslopeController(env.unwrapped.cfg, gains)
    total = 0.0
    while True:
        obs, r, term, trunc, info = env.step(ctl(obs))
        total += r
        assert np.all(np.isfinite(obs))
        if term or trunc:
            info["return"] = total
            info["truncated"] = trunc
            return info


def test_scripted_truth_approach_docks_inside_envelope() -> None:
    info = _fly("TriDAR/FinalApproach-v0", seed=0)
    assert info["termination"] == "docked"
    c = info["contact"]
    assert 0.05 <= c.closing_speed <= 0.10
    assert c.lateral_offset <= 0.10 and c.lateral_speed <= 0.04
    assert info["reward_success"] > 0 and info["return"] > 0


def test_too_fast_approach_is_a_collision() -> None:
    info = _fly("TriDAR/FinalApproach-v0", seed=0, gains=GlideslopeGains(v_final=0.3, slope=0.05, v_max=0.5))
    assert info["termination"] == "collision"
    assert info["contact"].closing_speed > 0.10
    assert info["reward_collision"] < 0


def test_far_behind_a_port_that_turned_away_is_not_a_contact() -> None:
    """The port plane of a tumbling target sweeps the sky: a chaser 10 m behind it, near its
    axis, is far from the target (it once ended the episode as a "collision" at 21 m range)."""
    env = gym.make("TriDAR/TumblingTarget-v0", perception="truth")
    env.reset(seed=0)
    u = env.unwrapped
    w = u.world
    T_lp = w.T_lvlh_port
    dock_offset = w.T_lvlh_dock[:3, 3] - w.state[:3]
    w.state = np.r_[T_lp[:3, 3] - 10.0 * T_lp[:3, 2] + 0.2 * T_lp[:3, 0] - dock_offset, np.zeros(3)]
    w._invalidate()
    c = w.contact()
    assert c.axial_distance < -9.0 and c.lateral_offset < 0.5 and w.hull_clearance() > 5.0
    assert u._termination() == ""
    # At the port plane, the same offset is a contact (outside the envelope at rest: collision).
    w.state = np.r_[T_lp[:3, 3] - 0.05 * T_lp[:3, 2] + 0.2 * T_lp[:3, 0] - dock_offset, np.zeros(3)]
    w._invalidate()
    assert u._termination() == "collision"


def _constant(env_id: str, action, seed: int = 0, **kw) -> dict:
    env = gym.make(env_id, perception="truth", **kw)
    env.reset(seed=seed)
    for _ in range(100_000):
        _, _, term, trunc, info = env.step(np.asarray(action, dtype=np.float32))
        if term or trunc:
            return info
    raise AssertionError("episode did not end")


def test_every_termination_cause_is_reachable() -> None:
    # Backing away at full thrust leaves the bounds.
    info = _constant("TriDAR/FinalApproach-v0", [0, 0, -1], env__max_range_m=40.0)
    assert info["termination"] == "out_of_bounds"
    # A lateral burn leaves the approach corridor.
    info = _constant("TriDAR/FinalApproach-v0", [1, 0, 0])
    assert info["termination"] == "corridor_exit"
    # A nearly empty tank runs dry.
    info = _constant("TriDAR/FinalApproach-v0", [0, 1, 0], dynamics__chaser__propellant_kg=0.01,
                     env__corridor_half_angle_deg=None)
    assert info["termination"] == "out_of_fuel"
    assert info["propellant_kg"] == 0.0


def test_hull_collision_detected_by_mesh_distance() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    env.reset(seed=0)
    w = env.unwrapped.world
    # Put the chaser centre 0.3 m off the lab module's hull (hull radius 0.5 m), far off the port axis.
    pts, nrm = env.unwrapped.target.sample_surface(2000, seed=0)
    i = int(np.argmin(pts[:, 1]))  # aft end of the lab, opposite the port
    p_lvlh = w.T_lvlh_target[:3, :3] @ (pts[i] + 0.3 * nrm[i])
    w.state = np.concatenate([p_lvlh, np.zeros(3)])
    w._memo.clear()
    assert w.hull_clearance() < 0
    _, _, term, _, info = env.step(np.zeros(3, dtype=np.float32))
    assert term and info["termination"] == "collision"


def test_bad_actions_and_call_order() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    with pytest.raises((RuntimeError, gym.error.ResetNeeded)):
        env.step(np.zeros(3, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0, 0], dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(4, dtype=np.float32))
    _, _, _, _, info = env.step(np.array([3.0, -2.0, 0.5], dtype=np.float32))
    assert info["clipped_actions"] == 2


def test_unknown_config_keys_fail_at_make() -> None:
    with pytest.raises(ConfigError, match="env.frame_skp"):
        gym.make("TriDAR/FinalApproach-v0", config={"env__frame_skp": 2})
    with pytest.raises(ConfigError, match="perception"):
        gym.make("TriDAR/FinalApproach-v0", perception="telepathy")


@pytest.mark.parametrize(
    ("config", "kwargs"),
    [
        ({"env__max_episode_steps": 10}, {}),
        ({"env": {"max_episode_steps": 10}}, {}),
        ({"env.max_episode_steps": 10}, {}),
        (None, {"env__max_episode_steps": 10}),
    ],
    ids=["flat", "nested", "dotted", "kwarg"],
)
def test_config_overrides_set_the_time_limit(config: dict | None, kwargs: dict) -> None:
    # The registered TimeLimit used to stay at the mission file's 3000 steps.
    env = gym.make("TriDAR/FinalApproach-v0", config=config, perception="truth", **kwargs)
    assert env.spec is not None and env.spec.max_episode_steps == 10
    env.reset(seed=0)
    for i in range(1, 11):
        _, _, terminated, truncated, _ = env.step(np.zeros(3, dtype=np.float32))
        assert not terminated and truncated == (i == 10)
    shorter = gym.make("TriDAR/FinalApproach-v0", perception="truth", max_episode_steps=4)
    shorter.reset(seed=0)
    assert [shorter.step(np.zeros(3, dtype=np.float32))[3] for _ in range(4)] == [False] * 3 + [True]


def test_vector_entry_point_takes_the_time_limit_from_the_config() -> None:
    envs = gym.make_vec("TriDAR/FinalApproach-v0", num_envs=2, vectorization_mode="vector_entry_point",
                        config={"env": {"max_episode_steps": 7}}, perception="truth")
    envs.reset(seed=0)
    truncated = [envs.step(np.zeros((2, 3), dtype=np.float32))[3].all() for _ in range(7)]
    assert truncated == [False] * 6 + [True]


def test_bad_configs_at_make_are_refused_in_one_line() -> None:
    make = gym.make
    cases: list[tuple[dict, str]] = [
        ({"config": {"env": 3}}, "env is 3, not a section"),  # used to drop the whole env section
        ({"config": {"env": None}}, "env is None, not a section"),
        ({"config": 3}, r"config=3 \(int\); expected a mission YAML path"),
        ({"config": {1: 2}}, "override key 1 is a int"),
        ({"config": {"render_mode": "human"}}, "render_mode: unknown key"),
        ({"config": {"env__initial__range_m": 1e300}}, r"env.initial.range_m: got 1e\+300, expected less than"),
        ({"config": {"env__frame_period_s": True}}, "env.frame_period_s: got True, expected a number, not a bool"),
        ({"env__frame_period_s": "0.5"}, "env.frame_period_s: got '0.5', expected a number, not a str"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ConfigError, match=match) as info:
            make("TriDAR/FinalApproach-v0", perception="truth", **kwargs)
        assert "\n" not in str(info.value)


def test_largest_accepted_physical_values_keep_rewards_finite() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth", config={
        "env": {"initial": {"range_m": 1e5}, "max_range_m": 1e5, "frame_period_s": 60.0, "frame_skip": 1000,
                "corridor_half_angle_deg": None},
        "dynamics__chaser": {"max_thrust_n": 1e5, "dry_mass_kg": 0.1, "propellant_kg": 1e6},
    })
    obs, _ = env.reset(seed=0)
    for _ in range(5):
        obs, reward, terminated, _, info = env.step(np.ones(3, dtype=np.float32))
        assert np.isfinite(obs).all() and np.isfinite(reward), info
        if terminated:
            break


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.array([np.inf, 0, 0]), "NaN or inf"),
        (np.array([1 + 2j, 0, 0]), "dtype complex128"),
        (np.array([True, False, True]), "dtype bool"),
        (["0.5", "0", "0"], "dtype <U3"),
        ([None, 0, 0], "dtype object"),
        ([10**400, 0, 0], "dtype object"),
        ([[1.0], [2.0, 3.0], 0.0], "not an array of numbers"),
        (np.zeros((3, 2)), r"shape \(3, 2\)"),
        (0.5, r"shape \(\)"),
        ({"x": 1}, "dtype object"),
    ],
)
def test_hostile_actions_are_refused_in_one_line(action: object, match: str) -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match) as info:
        env.step(action)
    assert "\n" not in str(info.value)
    obs, *_ = env.step(np.zeros(3, dtype=np.float32))  # the refused step changed nothing
    assert np.isfinite(obs).all() and env._steps == 1


def test_accepted_action_forms_and_huge_values() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth").unwrapped
    env.reset(seed=0)
    for action in ([0, 0, 1], np.zeros((1, 3), dtype=np.float16), np.array([[1e300], [-1e300], [0]])):
        obs, reward, _, _, info = env.step(action)
        assert np.isfinite(obs).all() and np.isfinite(reward)
    assert info["clipped_actions"] == 2
    vec = gym.make_vec("TriDAR/FinalApproach-v0", num_envs=2, vectorization_mode="vector_entry_point",
                       perception="truth")
    vec.reset(seed=0)
    for bad, match in ((np.zeros((3, 2)), "shape"), (np.full((2, 3), np.nan), "NaN"),
                       (np.zeros((2, 3), dtype=bool), "dtype bool")):
        with pytest.raises(ValueError, match=match):
            vec.step(bad)


def test_observation_never_nan_over_random_rollouts() -> None:
    for env_id in IDS:
        env = gym.make(env_id, perception="truth+noise")
        for seed in range(2):
            for obs, r in _rollout(env, seed, 200):
                assert np.all(np.isfinite(obs)) and np.isfinite(r)
                assert env.observation_space.contains(obs)


def test_observation_matches_truth_geometry() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    obs, info = env.reset(seed=4)
    s = observation_slices()
    c = info["contact"]
    p = obs[s["port_position_dock"]]
    assert p[2] == pytest.approx(c.axial_distance, abs=1e-4)
    assert np.hypot(p[0], p[1]) == pytest.approx(c.lateral_offset, abs=1e-4)
    np.testing.assert_allclose(obs[s["q_dock_port"]], [0, 1, 0, 0], atol=1e-6)  # facing the port
    np.testing.assert_array_equal(obs[s["mode_onehot"]], [0, 0, 1])
    assert obs[s["fuel_fraction"]][0] == 1.0


def test_render_rgb_array_shows_target() -> None:
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth", render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.zeros(3, dtype=np.float32))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    # The camera panel (right half) has shaded target pixels (grey, neither black nor white).
    right = frame[:, frame.shape[1] // 2 :].astype(int)
    grey = (np.abs(right[..., 0] - right[..., 1]) < 4) & (right[..., 0] > 40) & (right[..., 0] < 230)
    assert grey.sum() > 200


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_vector_envs_step(mode: str) -> None:
    envs = gym.make_vec("TriDAR/FinalApproach-v0", num_envs=2, vectorization_mode=mode,
                        vector_kwargs={} if mode == "sync" else {"context": "spawn"},
                        perception="truth")
    obs, _ = envs.reset(seed=[1, 2])
    assert obs.shape == (2, OBS_DIM)
    for _ in range(3):
        obs, r, _term, _trunc, _ = envs.step(np.zeros((2, 3), dtype=np.float32))
    assert np.all(np.isfinite(obs)) and r.shape == (2,)
    envs.close()


@pytest.mark.slow
def test_sb3_subproc_vec_env_pickles() -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    # "module:id" makes each spawned worker import tridar_env (which registers the ids) first.
    venv = make_vec_env("tridar_env:TriDAR/FinalApproach-v0", n_envs=2, vec_env_cls=SubprocVecEnv,
                        env_kwargs={"perception": "truth"}, vec_env_kwargs={"start_method": "spawn"})
    obs = venv.reset()
    obs, _r, _done, _ = venv.step(np.zeros((2, 3), dtype=np.float32))
    assert obs.shape == (2, OBS_DIM) and np.all(np.isfinite(obs))
    venv.close()


@pytest.mark.slow
def test_checkers_pass_on_the_full_tridar_pipeline() -> None:
    """The default perception (the TriDAR pipeline) passes both checkers too."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make("TriDAR/FinalApproach-v0")
    assert env.unwrapped.cfg.env.perception == "tridar"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped, warn=True)


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["TriDAR/FinalApproach-v0", "TriDAR/TumblingTarget-v0"])
def test_closed_loop_on_the_full_pipeline_is_finite_and_deterministic(env_id: str) -> None:
    """A short closed-loop run on the full pipeline: no NaN, valid tracking, same seed same run."""
    from agents.controllers import make_controller

    runs = []
    for _ in range(2):
        env = gym.make(env_id)
        ctl = make_controller("sync" if env.action_space.shape == (6,) else "glideslope", env.unwrapped.cfg)
        obs, _ = env.reset(seed=11)
        out = [obs]
        modes = []
        for _ in range(60):
            obs, r, term, trunc, info = env.step(ctl(obs))
            assert np.all(np.isfinite(obs)) and np.isfinite(r)
            out.append(obs)
            modes.append(info["mode"])
            if term or trunc:
                break
        runs.append(np.array(out))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert "tracking" in modes


def test_reset_builds_the_search_database_so_the_first_step_does_not(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the full pipeline, reset() builds what search needs (PAH database, near-symmetries):
    the first step of an episode searches without building anything (it used to stall ~1 s)."""
    import perception.estimation.pah as pah

    env = gym.make("TriDAR/FinalApproach-v0")
    env.unwrapped.target.cache.clear()  # as in a fresh process
    env.reset(seed=3)
    keys = set(env.unwrapped.target.cache)
    assert any(isinstance(k, tuple) and k and k[0] == "pah_db" for k in keys)
    sym = env.unwrapped.observer.pipeline.pah.near_symmetries()
    built: list[str] = []
    orig_build = pah.PAHDatabase.build

    def spy(*args, **kwargs):
        built.append("database")
        return orig_build(*args, **kwargs)

    monkeypatch.setattr(pah.PAHDatabase, "build", spy)
    _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert built == [] and info["mode"] in ("search", "tracking")
    assert env.unwrapped.observer.pipeline.pah.near_symmetries() is sym  # the cached array
