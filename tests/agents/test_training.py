"""Learning: train a few hundred steps, load the policy back safely, evaluate it; bad input."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from agents.campaign import CampaignConfig, build_specs, run_one
from agents.cli import main
from agents.training import (
    SB3Policy,
    TrainingConfig,
    evaluate,
    load_policy,
    load_training,
    train,
)
from perception.config import CONFIG_DIR, load_config
from tridar_env.env import OBS_DIM

TINY = {
    "name": "tiny",
    "algo": "ppo",
    "env_id": "TriDAR/FinalApproach-v0",
    "perception": "truth+noise",
    "config": {"env__frame_skip": 5, "env__initial__range_m": 5.0},
    "total_timesteps": 256,
    "n_envs": 2,
    "vec_env": "subproc",
    "seed": 3,
    "checkpoint_every_steps": 128,
    "net_arch": [32, 32],
    "activation": "tanh",
    "hyperparams": {"n_steps": 64, "batch_size": 64, "n_epochs": 2},
}


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A PPO policy trained for 256 steps on two subprocess envs (truth+noise)."""
    out = tmp_path_factory.mktemp("ppo")
    res = train(TrainingConfig(**TINY), out, progress=False)
    assert res.timesteps >= 256 and not res.interrupted
    return out


def test_train_writes_model_stats_config_checkpoints_and_tensorboard(trained):
    assert zipfile.is_zipfile(trained / "model.zip")
    assert load_config(trained / "training.yaml", model=TrainingConfig) == TrainingConfig(**TINY)
    with np.load(trained / "vecnormalize.npz", allow_pickle=False) as z:
        assert z["obs_mean"].shape == (OBS_DIM,) and float(z["obs_count"]) > 256
        assert np.all(z["obs_var"] >= 0) and bool(z["norm_obs"])
    ckpts = sorted(p.name for p in (trained / "checkpoints").iterdir())
    assert ckpts == ["model_128_steps.zip", "model_256_steps.zip",
                     "vecnormalize_128_steps.npz", "vecnormalize_256_steps.npz"]
    assert list((trained / "tb").rglob("events.out.tfevents.*"))


def test_loaded_policy_matches_sb3_and_vecnormalize(trained):
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    policy = load_policy(trained)
    assert isinstance(policy, SB3Policy) and policy.algo == "ppo"
    env = gym.make("TriDAR/FinalApproach-v0", perception="truth+noise", config=TINY["config"])
    obs = np.stack([env.reset(seed=s)[0] for s in range(5)])
    # Normalisation identical to VecNormalize restored from the same statistics.
    stats = np.load(trained / "vecnormalize.npz", allow_pickle=False)
    vn = VecNormalize(DummyVecEnv([lambda: env]), clip_obs=float(stats["clip_obs"]))
    vn.obs_rms.mean, vn.obs_rms.var = stats["obs_mean"], stats["obs_var"]
    ours = np.stack([policy.normalize(o) for o in obs])
    np.testing.assert_allclose(ours, vn.normalize_obs(obs).astype(np.float32), rtol=1e-6)
    # Actions identical to SB3's own loader (which we avoid because it unpickles).
    reference = PPO.load(trained / "model.zip", device="cpu")
    expected = np.stack([reference.predict(o, deterministic=True)[0] for o in ours])
    actions = np.stack([policy(o) for o in obs])
    np.testing.assert_array_equal(actions, expected)
    assert actions.shape == (5, 3) and np.all(np.abs(actions) <= 1.0)
    assert len({a.tobytes() for a in actions}) > 1  # depends on the observation
    # A checkpoint loads with its own statistics.
    ck = load_policy(trained / "checkpoints" / "model_128_steps.zip")
    assert ck._norm is not None and not np.array_equal(ck._norm[0], policy._norm[0])
    with pytest.raises(ValueError, match="observation has shape"):
        policy(obs[0][:5])


def test_loading_never_unpickles(trained, monkeypatch):
    import cloudpickle

    def refuse(*_a, **_k):
        raise AssertionError("unpickled")

    monkeypatch.setattr(cloudpickle, "loads", refuse)
    monkeypatch.setattr("pickle.loads", refuse)
    policy = load_policy(trained / "model.zip")
    assert policy(np.zeros(OBS_DIM, np.float32)).shape == (3,)


def test_evaluate_reads_the_policy_back(trained):
    table, summary = evaluate(trained, perception="truth+noise", episodes=2, seed=4, max_steps=30,
                              progress=False)
    assert list(table["index"]) == [0, 1] and summary["runs"] == 2
    assert set(table["cause"]) <= {"docked", "collision", "timeout", "out_of_bounds",
                                   "corridor_exit", "out_of_fuel"}
    assert (table["steps"] <= 30).all() and (table["delta_v_m_s"] > 0).all()
    # The same episodes as a campaign flying the policy (controller "sb3:<path>").
    camp = CampaignConfig(env_id="TriDAR/FinalApproach-v0", perception="truth+noise",
                          controller=f"sb3:{trained}", runs=2, seed=4, max_steps=30,
                          config=TINY["config"])
    row = run_one(build_specs(camp, [1])[0])
    assert row["delta_v_m_s"] == table.loc[1, "delta_v_m_s"]
    assert row["episode_return"] == table.loc[1, "episode_return"]
    # On a 2-worker LocalCluster: the same rows, in index order.
    par, _ = evaluate(trained, perception="truth+noise", episodes=2, seed=4, max_steps=30,
                      progress=False, workers=2)
    assert list(par["index"]) == [0, 1]
    np.testing.assert_array_equal(par["episode_return"], table["episode_return"])


def test_cli_evaluate_prints_the_campaign_summary(trained, capsys, tmp_path):
    code = main(["evaluate", str(trained / "model.zip"), "--perception", "truth", "--episodes", "1",
                 "--max-steps", "10", "--no-progress", "--out", str(tmp_path / "ev")])
    assert code == 0
    text = capsys.readouterr().out
    assert "Wilson 95% interval" in text and "success rate" in text
    assert json.loads((tmp_path / "ev" / "summary.json").read_text())["runs"] == 1


def test_sac_trains_and_loads(tmp_path):
    cfg = TrainingConfig(**{
        **TINY, "algo": "sac", "n_envs": 1, "vec_env": "dummy", "total_timesteps": 120,
        "checkpoint_every_steps": None, "activation": None,
        "hyperparams": {"learning_starts": 60, "batch_size": 32, "buffer_size": 1000},
    })
    train(cfg, tmp_path, progress=False)
    policy = load_policy(tmp_path)
    assert policy.algo == "sac" and policy(np.zeros(OBS_DIM, np.float32)).shape == (3,)
    with pytest.raises(ValueError, match="exists; pass --force"):
        train(cfg, tmp_path, progress=False)


def test_force_replaces_only_what_train_wrote(tmp_path):
    cfg = TrainingConfig(**{**TINY, "n_envs": 1, "vec_env": "dummy", "total_timesteps": 64,
                            "checkpoint_every_steps": 32,
                            "hyperparams": {"n_steps": 32, "batch_size": 32, "n_epochs": 1}})
    out = tmp_path / "run"
    train(cfg, out, progress=False)
    (out / "notes.txt").write_text("mine")
    (out / "checkpoints" / "best.zip").write_text("mine")
    with pytest.raises(ValueError, match="exists; pass --force"):
        train(cfg, out, progress=False)
    train(cfg.model_copy(update={"checkpoint_every_steps": 64}), out, progress=False, force=True)
    # The old run's checkpoints are gone, the user's files are not.
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == [
        "best.zip", "model_64_steps.zip", "vecnormalize_64_steps.npz"]
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "checkpoints" / "best.zip").read_text() == "mine"
    assert load_config(out / "training.yaml", model=TrainingConfig).checkpoint_every_steps == 64
    assert not list(out.glob(".*.tmp*"))
    assert json.loads((out / ".tridar-env-output").read_text())["kind"] == "train"


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    return path


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda p: p.write_bytes(b"not a zip at all"), "not a zip file"),
        (lambda p: _zip(p, {"readme.txt": b"hi"}), "lacks data, policy.pth"),
        (lambda p: _zip(p, {"data": b"{not json", "policy.pth": b""}), "not a stable-baselines3 model"),
        (lambda p: _zip(p, {"data": json.dumps({"x": 1}).encode(), "policy.pth": b""}),
         "does not know; expected PPO or SAC"),
        (lambda p: _zip(p, {"data": json.dumps({
            "clip_range": 0.2, "n_epochs": 1, "gadget": {":type:": "x", ":serialized:": "gARLAS4="},
        }).encode(), "policy.pth": b""}), "'gadget' is a pickled object"),
    ],
)
def test_bad_policy_files(tmp_path, capsys, make, words):
    path = tmp_path / "model.zip"
    make(path)
    with pytest.raises(ValueError, match=words):
        load_policy(path)
    code = main(["evaluate", str(path), "--env-id", "TriDAR/FinalApproach-v0", "--perception", "truth"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and words in err


def test_missing_policy_file(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "nope.zip"), "--env-id", "TriDAR/FinalApproach-v0"]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, words",
    [
        (None, "does not exist"),
        ("algo: [ppo\n", "not valid YAML"),
        (yaml.safe_dump({**TINY, "algo": "dqn"}), "algo: got 'dqn'"),
        (yaml.safe_dump({**TINY, "hyperparams": {"n_stepz": 3}}), "hyperparams.n_stepz=3 is not a PPO argument"),
        (yaml.safe_dump({**TINY, "config": {"env__frame_skp": 2}}), "frame_skp: unknown key"),
        (yaml.safe_dump({**TINY, "env_id": "CartPole-v1"}), "env_id='CartPole-v1' is not registered"),
    ],
)
def test_cli_bad_training_yaml(tmp_path, capsys, content, words):
    path = tmp_path / "t.yaml"
    if content is not None:
        path.write_text(content)
    out = tmp_path / "out"
    assert main(["train", str(path), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tridar-env train: error:") and words in err
    assert not out.exists()


def test_shipped_training_configs_validate():
    paths = sorted((CONFIG_DIR / "training").glob("*.yaml"))
    assert {load_training(p).algo for p in paths} == {"ppo", "sac"}
    for p in paths:
        cfg = load_training(p)
        assert cfg.perception == "truth+noise" and cfg.n_envs >= 2
        # Many envs only where they come batched in one process (two cores).
        assert cfg.n_envs == 2 or cfg.vec_env in ("auto", "batched"), (p.name, cfg.n_envs, cfg.vec_env)


def test_same_seed_same_policy(tmp_path):
    cfg = TrainingConfig(**{**TINY, "n_envs": 2, "vec_env": "dummy", "total_timesteps": 128,
                            "checkpoint_every_steps": None})
    a = load_policy(train(cfg, tmp_path / "a", progress=False).out_dir)
    b = load_policy(train(cfg, tmp_path / "b", progress=False).out_dir)
    c = load_policy(train(cfg.model_copy(update={"seed": 4}), tmp_path / "c", progress=False).out_dir)
    obs = np.linspace(-1, 1, OBS_DIM).astype(np.float32)
    np.testing.assert_array_equal(a._norm[0], b._norm[0])
    assert np.array_equal(a(obs), b(obs)) and not np.array_equal(a(obs), c(obs))


def test_behaviour_cloning_warm_start_imitates_the_controller(tmp_path):
    """The pretrained policy reproduces the glideslope's actions on its own demonstration states
    far better than the same network without pretraining, and its observation statistics are
    those of the demonstrations."""
    from agents.training import PretrainConfig, collect_demonstrations, validate_training

    pre = {"episodes": 3, "action_noise": 0.05, "epochs": 60, "learning_rate": 3e-3, "log_std": -2.0}
    base = {**TINY, "vec_env": "dummy", "total_timesteps": 1, "checkpoint_every_steps": None,
            "config": {"env__frame_skip": 5, "env__initial__range_m": 6.0}}
    cold = load_policy(train(TrainingConfig(**base), tmp_path / "cold", progress=False).out_dir)
    cfg = TrainingConfig(**{**base, "pretrain": pre})
    warm_dir = train(cfg, tmp_path / "warm", progress=False).out_dir
    warm = load_policy(warm_dir)
    demos = collect_demonstrations(cfg, validate_training(cfg))
    assert len(demos.outcomes) == 3 and len(demos.obs) == len(demos.actions) > 50

    def mse(policy) -> float:
        return float(np.mean([(policy(o) - a) ** 2 for o, a in zip(demos.obs, demos.actions)]))

    assert mse(warm) < 0.2 * mse(cold)
    # VecNormalize saw the demonstration states (plus the first reset of the training envs).
    np.testing.assert_allclose(warm._norm[0], demos.obs.mean(axis=0), atol=0.05 * (1 + np.abs(demos.obs).max()))
    stats = json.loads((warm_dir / "pretrain.json").read_text())
    assert stats["episodes"] == 3 and stats["samples"] == len(demos.obs) and stats["log_std"] == -2.0
    assert PretrainConfig(**pre).controller == "glideslope"


def test_dagger_rounds_fit_the_policy_to_the_controller_on_its_own_states(tmp_path):
    """DAgger: on states the trained policy visits itself (fresh seeds, the controller labelling
    alongside), its actions are nearer the controller's after DAgger rounds than after plain
    cloning of the same demonstrations for as many passes in all; every round's states join the
    data set. (Measured: squared action error 0.0052 after three rounds, 0.011-0.015 after plain
    cloning of 120-160 passes.)"""
    from agents.pretrain import fly_labelled
    from agents.training import validate_training

    pre = {"episodes": 2, "action_noise": 0.05, "epochs": 40, "learning_rate": 3e-3, "log_std": -2.0}
    base = {**TINY, "vec_env": "dummy", "total_timesteps": 1, "checkpoint_every_steps": None,
            "config": {"env__frame_skip": 5, "env__initial__range_m": 6.0}}
    plain_cfg = TrainingConfig(**{**base, "pretrain": {**pre, "epochs": 40 + 3 * 40}})
    dag_cfg = TrainingConfig(**{**base, "pretrain": {**pre, "dagger_rounds": 3, "dagger_episodes": 3,
                                                      "dagger_epochs": 40}})
    plain_dir = train(plain_cfg, tmp_path / "plain", progress=False).out_dir
    dag_dir = train(dag_cfg, tmp_path / "dagger", progress=False).out_dir
    stats = json.loads((dag_dir / "pretrain.json").read_text())
    rounds = stats["dagger"]
    assert [r["round"] for r in rounds] == [1, 2, 3] and all(r["episodes"] == 3 for r in rounds)
    assert stats["samples"] < rounds[0]["samples"] < rounds[1]["samples"] < rounds[2]["samples"]
    mission = validate_training(plain_cfg)

    def error_on_own_states(run_dir) -> float:
        policy = load_policy(run_dir)
        flown = fly_labelled(plain_cfg, mission, [777, 778, 779], np.random.default_rng(0), policy=policy)
        return float(np.mean((np.stack([policy(o) for o in flown.obs]) - flown.actions) ** 2))

    assert error_on_own_states(dag_dir) < 0.7 * error_on_own_states(plain_dir)


def test_frozen_observation_statistics_stay_as_the_cloning_left_them(tmp_path):
    """freeze_obs_stats: PPO's rollouts leave the saved observation statistics as they were when
    the cloning ended; without it they move."""
    from agents.policies import load_stats

    pre = {"episodes": 1, "epochs": 2}
    base = {**TINY, "vec_env": "dummy", "checkpoint_every_steps": None,
            "config": {"env__frame_skip": 5, "env__initial__range_m": 6.0}}

    def stats(name: str, steps: int, freeze: bool) -> np.ndarray:
        cfg = TrainingConfig(**{**base, "total_timesteps": steps,
                                "pretrain": {**pre, "freeze_obs_stats": freeze}})
        return load_stats(train(cfg, tmp_path / name, progress=False).out_dir / "vecnormalize.npz")["obs_mean"]

    cloned = stats("cloned", 1, True)
    np.testing.assert_array_equal(stats("frozen", 512, True), cloned)
    assert not np.array_equal(stats("moving", 512, False), cloned)


def test_pretrain_is_only_for_ppo_and_names_a_known_controller():
    from agents.training import validate_training
    from perception.config import ConfigError

    with pytest.raises(ConfigError, match="pretrain is set with algo='sac'"):
        validate_training(TrainingConfig(**{**TINY, "algo": "sac", "hyperparams": {}, "pretrain": {}}))
    with pytest.raises(ConfigError, match="pretrain.controller='nope' is unknown"):
        validate_training(TrainingConfig(**{**TINY, "pretrain": {"controller": "nope"}}))
