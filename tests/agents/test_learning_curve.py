"""The learning curve of a training run: one row per rollout that counts the episodes right."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agents.learning_curve import COLUMNS, OUTCOMES, plot_learning_curve, read_learning_curve
from agents.training import TrainingConfig, train

SHORT = {
    "name": "curve",
    "algo": "ppo",
    "env_id": "TriDAR/FinalApproach-v0",
    "perception": "truth",
    # Every episode is cut by the time limit after 10 steps (2 s at 20 m, too short to reach
    # anything at full thrust): the counts are known.
    "config": {"env__max_episode_steps": 10, "env__initial__range_m": 20.0},
    "total_timesteps": 128,
    "n_envs": 2,
    "vec_env": "dummy",
    "seed": 1,
    "checkpoint_every_steps": None,
    "net_arch": [16],
    "hyperparams": {"n_steps": 16, "batch_size": 32, "n_epochs": 1},
}


def test_train_writes_one_row_per_rollout_with_the_episode_counts(tmp_path):
    out = tmp_path / "run"
    train(TrainingConfig(**SHORT), out, progress=False)
    c = read_learning_curve(out / "learning_curve.csv")
    lines = (out / "learning_curve.csv").read_text().splitlines()
    assert lines[1].startswith("32,") and lines[-1].startswith("128,")  # counts written whole
    steps = c["timesteps"]
    assert np.array_equal(steps, 32.0 * np.arange(1, 5))
    # Two envs, each ending an episode every 10 steps: 2 * floor(steps per env / 10) so far.
    assert np.array_equal(c["episodes"], 2.0 * np.floor(steps / 2 / 10))
    assert np.all(np.diff(c["wall_s"]) >= 0) and c["wall_s"][0] >= 0
    fractions = np.stack([c[k] for k in OUTCOMES])
    done = c["episodes"] > 0
    assert np.allclose(fractions[:, done].sum(axis=0), 1.0)
    assert np.all(np.isnan(fractions[:, ~done]))
    assert np.all(c["truncated"][done] == 1.0) and np.all(c["length_mean"][done] == 10.0)
    assert np.all(np.isfinite(c["return_mean"][done]))
    assert (out / "learning_curve.png").stat().st_size > 1000


def test_a_curve_is_never_appended_to_another_runs(tmp_path):
    from agents.learning_curve import LearningCurve

    p = tmp_path / "learning_curve.csv"
    p.write_text("mine\n")
    with pytest.raises(ValueError, match="learning_curve.csv exists"):
        LearningCurve(p)
    assert p.read_text() == "mine\n"
    with pytest.raises(ValueError, match="window=0"):
        LearningCurve(window=0)


@pytest.mark.parametrize(
    "text, words",
    [
        ("a,b\n1,2\n", "expected the columns"),
        ("", "expected the columns"),
        (",".join(COLUMNS) + "\n" + ",".join(["1"] * (len(COLUMNS) - 1)) + "\n", "line 2 has"),
        (",".join(COLUMNS) + "\n" + ",".join(["x"] * len(COLUMNS)) + "\n", "not a number"),
    ],
)
def test_bad_curve_files_are_named(tmp_path, text, words):
    p = tmp_path / "c.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=words) as e:
        read_learning_curve(p)
    assert str(p) in str(e.value)


def test_plot_of_a_written_curve(tmp_path):
    p = tmp_path / "c.csv"
    rows = [[1000 * k, 10.0 * k, 5 * k, -10 + k, 100, 0.1 * k, 0.1, 0, 0, 0, 0, 0, 0.9 - 0.2 * k]
            for k in range(1, 6)]
    assert len(rows[0]) == len(COLUMNS)
    p.write_text(",".join(COLUMNS) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    c = read_learning_curve(p)
    assert c["docked"][-1] == pytest.approx(0.5) and not math.isnan(c["return_mean"][0])
    png = plot_learning_curve(p, tmp_path / "c.png", "title")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
