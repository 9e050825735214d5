"""The baseline table (``tridar-env evaluate --table``, issue 22): its counts are the runs' own, its
Wilson interval the campaign summary's, its gap truth minus pipeline, its commands reproduce
their lines, and bad specs or arguments fail in one line naming what is wrong."""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from agents import baseline_table as bt
from agents.campaign_spec import CampaignConfig, build_specs
from agents.campaign_summary import summarize
from agents.cli import main
from agents.episode import wilson_interval
from agents.runner import run_one
from perception.config import CONFIG_DIR, ConfigError

FA = "TriDAR/FinalApproach-v0"


def _spec(tmp_path: Path, rows: list[dict], name: str = "spec.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump({"rows": rows}))
    return p


def _cli(command: str) -> list[str]:
    """A table line's reproducing command as ``main`` arguments."""
    words = shlex.split(command)
    assert words[:2] == ["tridar-env", "evaluate"]
    return words[1:]


# ---------------------------------------------------------------------------------------------
# End to end on truth
# ---------------------------------------------------------------------------------------------
def test_truth_line_counts_equal_the_campaign_runs_and_a_mixed_line_too(tmp_path: Path, capsys) -> None:
    path = _spec(tmp_path, [{"env_id": FA, "policy": "glideslope", "perceptions": ["truth"],
                             "episodes": 2, "seed": 0}])
    spec = bt.load_spec(path)
    (line,) = bt.run_table(spec, path, progress=False)
    # The same episodes, flown one by one as runs of a campaign without dispersions.
    camp = CampaignConfig(name="c", env_id=FA, perception="truth", controller="glideslope", runs=2, seed=0)
    runs = [run_one(s) for s in build_specs(camp)]
    assert list(line.table["env_seed"]) == [r["env_seed"] for r in runs]
    assert list(line.table["steps"]) == [r["steps"] for r in runs]
    k = sum(r["success"] for r in runs)
    assert line.figures["runs"] == 2 and line.figures["succeeded"] == k == 2
    assert line.figures["delta_v_median_m_s"] == pytest.approx(np.median([r["delta_v_m_s"] for r in runs]))
    assert line.figures["contact_closing_speed_median_m_s"] == pytest.approx(
        np.median([r["contact_closing_speed"] for r in runs]))
    assert line.gap_pp is None  # no pipeline line in this row
    assert line.training is None

    # Mixed: a step cap between the two runs' docking steps docks one and times the other out.
    steps = sorted(r["steps"] for r in runs)
    assert steps[0] < steps[1], steps
    cap = (steps[0] + steps[1]) // 2
    mixed = bt.run_table(spec, path, max_steps=cap, progress=False)[0]
    table = mixed.table
    assert sorted(table["cause"]) == ["docked", "timeout"]
    assert int(table.loc[table["docked"], "steps"].iloc[0]) == steps[0]
    assert mixed.figures["succeeded"] == int(table["success"].sum()) == 1
    assert mixed.figures["docked"] == 1 and mixed.figures["runs"] == 2
    lo, hi = wilson_interval(1, 2)
    assert (mixed.figures["wilson95_low"], mixed.figures["wilson95_high"]) == (lo, hi)
    s = summarize(table)
    assert (s["wilson95_low"], s["wilson95_high"]) == (lo, hi)
    docked = table[table["docked"]]
    assert mixed.figures["contact_closing_speed_median_m_s"] == pytest.approx(
        float(docked["contact_closing_speed"].iloc[0]))
    assert mixed.command == (f"tridar-env evaluate --table {path} --only 0 --perception truth "
                             f"--episodes 2 --seed 0 --max-steps {cap}")

    # Its command reproduces the line alone, with the same figures.
    out = tmp_path / "out"
    assert main([*_cli(mixed.command), "--no-progress", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("| 0 | TriDAR/FinalApproach-v0 |") == 1
    doc = json.loads((out / "rows.json").read_text())
    (row,) = doc["lines"]
    assert (row["succeeded"], row["runs"], row["max_steps"]) == (1, 2, cap)
    assert (row["wilson95_low"], row["wilson95_high"]) == (lo, hi)
    assert row["command"] == mixed.command
    assert (out / "table.md").read_text().startswith("| # | env id |")


# ---------------------------------------------------------------------------------------------
# Figures, on given rows
# ---------------------------------------------------------------------------------------------
def _rows(causes: list[str], closing: list[float], lateral: list[float]) -> pd.DataFrame:
    return pd.DataFrame([{
        "index": i, "outcome": "error" if c == "error" else ("docked" if c == "docked" else "failed"),
        "cause": c, "docked": c == "docked", "success": c == "docked", "delta_v_m_s": 0.1 * (i + 1),
        "contact_closing_speed": v, "contact_lateral_offset": w,
    } for i, (c, v, w) in enumerate(zip(causes, closing, lateral))])


def test_figures_wilson_is_the_summary_s_and_contacts_are_the_docked_runs() -> None:
    causes = ["docked", "collision", "docked", "timeout", "docked", "error", "out_of_fuel"]
    closing = [0.05, 0.50, 0.07, math.nan, 0.09, math.nan, math.nan]
    lateral = [0.01, 0.40, 0.02, math.nan, 0.03, math.nan, math.nan]
    table = _rows(causes, closing, lateral)
    f = bt.line_figures(table)
    s = summarize(table)
    assert (f["runs"], f["succeeded"], f["errors"]) == (7, 3, 1)
    assert (f["wilson95_low"], f["wilson95_high"]) == (s["wilson95_low"], s["wilson95_high"])
    assert (f["wilson95_low"], f["wilson95_high"]) == wilson_interval(3, 7)
    assert f["contact_closing_speed_median_m_s"] == pytest.approx(0.07)
    assert s["contact_closing_speed_median_m_s"] == pytest.approx(0.08)  # the collision counts there
    assert f["contact_lateral_offset_p90_m"] == pytest.approx(np.percentile([0.01, 0.02, 0.03], 90))
    assert f["delta_v_median_m_s"] == pytest.approx(0.4)
    md = bt.format_markdown([bt.Line(0, bt.BaselineRow(env_id=FA, policy="lqr", perceptions=["truth"],
                                                       episodes=7), "truth", table, f, None, None, "x")])
    assert "| 42.9 | [15.8, 75.0] |" in md
    assert "1 episodes crashed" in md


def test_gap_is_truth_minus_pipeline() -> None:
    assert bt.pipeline_gap(0.9, 0.6) == pytest.approx(30.0)
    assert bt.pipeline_gap(0.25, 0.75) == pytest.approx(-50.0)
    assert bt.pipeline_gap(None, 0.5) is None
    assert bt.pipeline_gap(0.5, None) is None
    assert bt.pipeline_gap(math.nan, 0.5) is None


def test_gap_column_of_each_row(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    wins = {("glideslope", "truth"): 4, ("glideslope", "truth+noise"): 3,
            ("glideslope", "tridar"): 1, ("lqr", "truth"): 2}

    def fly(row, perception, tick, workers, scheduler):
        k = wins[(row.policy, perception)]
        return _rows(["docked"] * k + ["timeout"] * (row.episodes - k), [0.05] * row.episodes,
                     [0.01] * row.episodes)

    monkeypatch.setattr(bt, "_fly", fly)
    path = _spec(tmp_path, [
        {"env_id": FA, "policy": "glideslope", "perceptions": ["truth", "truth+noise", "tridar"], "episodes": 4},
        {"env_id": FA, "policy": "lqr", "perceptions": ["truth"], "episodes": 4},
    ])
    lines = bt.run_table(bt.load_spec(path), path, progress=False)
    assert [(ln.row, ln.perception, ln.figures["succeeded"]) for ln in lines] == [
        (0, "truth", 4), (0, "truth+noise", 3), (0, "tridar", 1), (1, "truth", 2)]
    assert [ln.gap_pp for ln in lines] == [75.0, 75.0, 75.0, None]
    assert "| +75.0 |" in bt.format_markdown(lines)
    # Only the pipeline line: no truth score, no gap.
    assert [ln.gap_pp for ln in bt.run_table(bt.load_spec(path), path, perception="tridar",
                                             progress=False)] == [None]


# ---------------------------------------------------------------------------------------------
# The spec
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("row", "words"),
    [
        ({"perceptions": ["truth", "lidar"]}, ["rows.0.perceptions.1", "'lidar'", "'truth+noise'"]),
        ({"policy": "glidescope"}, ["rows.0.policy", "'glidescope'", "glideslope", "sb3:<path"]),
        ({"env_id": "TriDAR/Docking-v9"}, ["rows.0.env_id", "'TriDAR/Docking-v9'", FA]),
        ({"episodes": 0}, ["rows.0.episodes", "got 0", "greater than or equal to 1"]),
        ({"perceptions": ["truth", "truth"]}, ["rows.0.perceptions", "['truth', 'truth']", "each perception once"]),
        ({"perceptions": []}, ["rows.0.perceptions", "[]", "at least 1"]),
        ({"episdoes": 3}, ["rows.0.episdoes", "unknown key", "3"]),
    ],
)
def test_spec_errors_name_field_value_and_expectation(tmp_path: Path, row: dict, words: list[str]) -> None:
    base = {"env_id": FA, "policy": "glideslope", "perceptions": ["truth"]}
    path = _spec(tmp_path, [{**base, **row}])
    with pytest.raises(ConfigError) as err:
        bt.load_spec(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    for w in words:
        assert w in msg, (w, msg)


def test_spec_refuses_a_missing_policy_and_a_bad_selection(tmp_path: Path) -> None:
    path = _spec(tmp_path, [{"env_id": FA, "policy": f"sb3:{tmp_path / 'nope'}", "perceptions": ["truth"]}])
    with pytest.raises(FileNotFoundError, match="nope"):
        bt.load_spec(path)
    spec = bt.BaselineSpec(rows=[bt.BaselineRow(env_id=FA, policy="lqr", perceptions=["truth", "tridar"])])
    assert bt.select(spec) == [(0, "truth"), (0, "tridar")]
    with pytest.raises(ValueError, match="--only 3: the spec has rows 0..0"):
        bt.select(spec, [3])
    with pytest.raises(ValueError, match="perception 'flash'"):
        bt.select(spec, None, "flash")


def test_shipped_spec_covers_every_id_on_truth_noise_and_pipeline() -> None:
    from tridar_env.registration import ENV_IDS

    spec = bt.load_spec(CONFIG_DIR / "baselines.yaml")  # validates every line's mission as well
    assert {r.env_id for r in spec.rows} == set(ENV_IDS)
    for r in spec.rows:
        assert {"truth", "truth+noise", "tridar"} <= set(r.perceptions), r
        assert not r.is_sb3  # no trained model ships with the repository
    assert {(r.env_id, r.policy) for r in spec.rows} >= {(FA, "glideslope"), (FA, "lqr"),
                                                          ("TriDAR/FlyAround-v0", "fly_around")}


# ---------------------------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------------------------
def test_cli_refuses_both_or_neither_in_one_line(tmp_path: Path, capsys) -> None:
    path = _spec(tmp_path, [{"env_id": FA, "policy": "glideslope", "perceptions": ["truth"]}])
    for argv, words in (
        (["evaluate", "runs/train/x", "--table", str(path)], ["MODEL 'runs/train/x'", "--table", "expected one"]),
        (["evaluate"], ["no MODEL and no --table"]),
        (["evaluate", "m.zip", "--only", "0"], ["--only 0", "with --table"]),
        (["evaluate", "--table", str(path), "--env-id", FA], ["--env-id", "--only ROW"]),
        (["evaluate", "--table", str(path), "--only", "1"], ["--only 1", "rows 0..0"]),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("tridar-env evaluate: error: "), err
        for w in words:
            assert w in err, (w, err)
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    assert main(["evaluate", "--table", str(path), "--no-progress", "--out", str(theirs)]) == 2
    assert "not created by tridar-env" in capsys.readouterr().err
    assert sorted(p.name for p in theirs.iterdir()) == ["notes.txt"]


# ---------------------------------------------------------------------------------------------
# A learned policy: its line is `tridar-env evaluate MODEL ...`, its training figures the folder's
# ---------------------------------------------------------------------------------------------
def test_sb3_line_equals_evaluate_and_reads_its_training(tmp_path: Path, capsys) -> None:
    from agents.training import TrainingConfig, train

    cfg = TrainingConfig(
        name="tiny", algo="ppo", env_id=FA, perception="truth", config={"env__frame_skip": 5},
        total_timesteps=128, n_envs=1, vec_env="dummy", seed=1, net_arch=[16],
        hyperparams={"n_steps": 64, "batch_size": 64, "n_epochs": 1},
    )
    run = tmp_path / "run"
    res = train(cfg, run, progress=False)
    info = bt.training_info(run)
    assert info.steps == res.timesteps == 128
    assert info.wall_time_s is not None and 0.0 < info.wall_time_s <= res.wall_time_s + 0.5
    # The wall time is the learning curve's last row; without the curve, TensorBoard's.
    from agents.learning_curve import read_learning_curve

    assert info.wall_time_s == read_learning_curve(run / "learning_curve.csv")["wall_s"][-1]
    (run / "learning_curve.csv").rename(tmp_path / "curve.csv")
    tb_info = bt.training_info(run)
    assert tb_info.steps == 128 and tb_info.wall_time_s is not None
    assert 0.0 < tb_info.wall_time_s <= res.wall_time_s + 0.5
    (tmp_path / "curve.csv").rename(run / "learning_curve.csv")

    path = _spec(tmp_path, [{"env_id": FA, "policy": f"sb3:{run}", "perceptions": ["truth"],
                             "episodes": 2, "seed": 5, "max_steps": 20}])
    (line,) = bt.run_table(bt.load_spec(path), path, progress=False)
    assert line.command == (f"tridar-env evaluate {run} --env-id {FA} --perception truth "
                            "--episodes 2 --seed 5 --max-steps 20")
    assert line.training == info
    out = tmp_path / "eval"
    assert main([*_cli(line.command), "--no-progress", "--out", str(out)]) == 0
    capsys.readouterr()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == line.figures["runs"] == 2
    assert summary["succeeded"] == line.figures["succeeded"]
    assert summary["delta_v_median_m_s"] == pytest.approx(line.figures["delta_v_median_m_s"])
    md = bt.format_markdown([line])
    assert "| 128 |" in md and f"`sb3:{run}`" in md
