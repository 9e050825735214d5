"""Monte Carlo campaigns: dispersions, seeds, Dask execution, Parquet rows, resume, bad input."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from agents.campaign import (
    CampaignConfig,
    Dispersion,
    build_specs,
    env_seed,
    load_campaign,
    run_campaign,
    run_one,
    sample_overrides,
    summarize,
)
from agents.controllers import make_controller
from agents.episode import wilson_interval
from agents.glideslope import GlideslopeController
from perception.config import CONFIG_DIR, ConfigError, load_config
from agents.cli import main

# Short runs: the chaser starts 4-6 m from the port, and 120 steps (24 s) cap every run.
TINY = {
    "name": "tiny",
    "env_id": "TriDAR/FinalApproach-v0",
    "perception": "truth+noise",
    "controller": "glideslope",
    "runs": 4,
    "seed": 5,
    "max_steps": 120,
    # Position noise at the centre of mass, so that max_pos_err_m (a centre-of-mass error) is
    # bounded by the position sigmas alone.
    "config": {"env__initial__range_dispersion_m": 0.0, "env__truth_noise_reference": "center_of_mass"},
    "dispersions": {
        "env__initial__range_m": {"uniform": [4.0, 6.0]},
        "env__truth_noise_position_m": [0.005, 0.02],
    },
}


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def dead_pid() -> int:
    """The id of a process that has ended."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def frame(df: pd.DataFrame) -> pd.DataFrame:
    """A results table without the wall-clock column (the only non-reproducible one)."""
    return df.drop(columns=["wall_time_s"]).sort_values("index").reset_index(drop=True)


# ---------------------------------------------------------------------------------------------
# Dispersions and seeds
# ---------------------------------------------------------------------------------------------
def test_dispersion_forms_sample_inside_their_support():
    rng = np.random.default_rng(0)
    u = Dispersion.parse("k", {"uniform": [2.0, 3.0]})
    assert all(2.0 <= u.sample(rng) <= 3.0 for _ in range(200))
    vec = Dispersion.parse("k", {"uniform": [[0, -1, 5], [1, 0, 5]]}).sample(rng)
    assert len(vec) == 3 and 0 <= vec[0] <= 1 and -1 <= vec[1] <= 0 and vec[2] == 5
    n = Dispersion.parse("k", {"normal": [0.0, 10.0], "clip": [-1.0, None]})
    draws = np.array([n.sample(rng) for _ in range(500)])
    assert draws.min() == -1.0 and draws.max() > 5.0  # clipped below only
    lu = [Dispersion.parse("k", {"loguniform": [1e-3, 1e-1]}).sample(rng) for _ in range(500)]
    assert 1e-3 <= min(lu) and max(lu) <= 1e-1 and np.median(lu) < 0.02  # log-spread, not linear
    w = Dispersion.parse("k", {"choice": ["a", "b"], "weights": [1, 0]})
    assert {w.sample(rng) for _ in range(50)} == {"a"}
    assert Dispersion.parse("k", [None, 60.0]).kind == "choice"
    assert Dispersion.parse("k", 3.0).sample(rng) == 3.0
    assert Dispersion.parse("k", {"center_m": [0, 0, 1], "radius_m": 0.2}).kind == "constant"


@pytest.mark.parametrize(
    "spec, words",
    [
        ({"uniform": [3.0, 2.0]}, "lower <= upper"),
        ({"normal": [1.0, -1.0]}, "sigma >= 0"),
        ({"uniform": [1.0]}, "[a, b]"),
        ({"uniform": [1, 2], "normal": [1, 2]}, "exactly one"),
        ({"uniform": [1, 2], "clip": 3}, "clip"),
        ({"choice": [1, 2], "weights": [1]}, "weights"),
        ([], "empty list"),
    ],
)
def test_bad_dispersions_name_key_and_value(spec, words):
    with pytest.raises(ValueError, match="dispersions.env__x") as e:
        Dispersion.parse("env__x", spec)
    assert words in str(e.value)


def test_run_seeds_are_order_independent_and_per_key():
    cfg = CampaignConfig(**TINY)
    all_specs = build_specs(cfg)
    assert build_specs(cfg, [3])[0] == all_specs[3]
    bigger = build_specs(CampaignConfig(**{**TINY, "runs": 9}))
    assert bigger[:4] == all_specs
    assert len({s.env_seed for s in bigger}) == 9
    assert all_specs[2].env_seed == env_seed(5, 2)
    # The run seed is the i-th child SeedSequence(seed).spawn would give.
    child = np.random.SeedSequence(5).spawn(3)[2]
    assert child.spawn_key == (2,) and child.entropy == 5
    # A new dispersion key leaves the others' samples unchanged.
    more = CampaignConfig(**{**TINY, "dispersions": {
        **TINY["dispersions"], "env__initial__lateral_dispersion_m": {"uniform": [0, 1]}}})
    for i in range(4):
        a, b = sample_overrides(cfg, i), sample_overrides(more, i)
        assert all(a[k] == b[k] for k in a)
    # A different campaign seed gives different draws.
    other = CampaignConfig(**{**TINY, "seed": 6})
    assert sample_overrides(other, 0) != sample_overrides(cfg, 0)


# ---------------------------------------------------------------------------------------------
# Controllers registry
# ---------------------------------------------------------------------------------------------
def test_make_controller_by_name_and_clear_errors(monkeypatch):
    cfg = load_config("final_approach", env__perception="truth")
    assert isinstance(make_controller("glideslope", cfg), GlideslopeController)
    assert isinstance(make_controller("agents.glideslope:GlideslopeController", cfg), GlideslopeController)
    with pytest.raises(ValueError, match="unknown; expected one of fly_around, glideslope, lqr, sync"):
        make_controller("pid", cfg)
    import agents.controllers as ac

    monkeypatch.setitem(ac.CONTROLLERS, "later", "agents.not_written_yet:Later")
    with pytest.raises(ValueError, match="'later' needs module 'agents.not_written_yet'"):
        make_controller("later", cfg)


# ---------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------
def test_run_one_turns_a_crash_into_an_error_row():
    cfg = CampaignConfig(**{**TINY, "controller": "agents.nowhere:Nothing"})
    row = run_one(build_specs(cfg, [0])[0])
    assert row["outcome"] == "error" and "agents.nowhere" in row["cause"] and row["index"] == 0


def test_campaign_on_local_cluster_rows_resume_and_no_duplicates(tmp_path):
    cfg = CampaignConfig(**TINY)
    # Reference: the whole campaign in a serial loop.
    ref = run_campaign(cfg, tmp_path / "serial", serial=True, progress=False, plots=False)
    assert ref.complete and sorted(ref.ran) == [0, 1, 2, 3]

    # Interrupted on a LocalCluster after two finished runs (as Ctrl-C would).
    out = tmp_path / "dask"
    seen: list[int] = []

    def interrupt(row):
        seen.append(row["index"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_campaign(cfg, out, workers=2, progress=False, on_result=interrupt)
    parts = sorted(p.name for p in (out / "parts").glob("run_*.parquet"))
    assert len(parts) == 2 and not (out / "results.parquet").exists()
    # A write cut short leaves a temporary file (its writer's pid in the name, the process gone):
    # it must be ignored and cleaned.
    (out / "parts" / f".run_000009.parquet.{dead_pid()}.tmp").write_bytes(b"partial")

    res = run_campaign(cfg, out, workers=2, progress=False)
    assert sorted(res.ran) == sorted(set(range(4)) - set(seen))  # only the missing ones ran
    assert res.complete
    table = pd.read_parquet(out / "results.parquet")
    assert list(table["index"]) == [0, 1, 2, 3]  # one row per run, nothing duplicated
    assert not list((out / "parts").glob("*.tmp"))
    # Bitwise the same rows as the uninterrupted serial campaign.
    pd.testing.assert_frame_equal(frame(table), frame(ref.table))

    # Correct rows: seeds, dispersions, outcomes and the figures the summary is built from.
    for _, r in table.iterrows():
        assert r["env_seed"] == env_seed(cfg.seed, int(r["index"]))
        assert 4.0 <= r["disp__env__initial__range_m"] <= 6.0
        assert r["disp__env__truth_noise_position_m"] in (0.005, 0.02)
        assert r["outcome"] in ("docked", "failed") and r["docked"] == (r["cause"] == "docked")
        assert r["track_losses"] == 0 and r["symmetry_switches"] == 0  # no pipeline on truth+noise
        assert r["steps"] <= cfg.max_steps and r["delta_v_m_s"] > 0
        assert 0 < r["rms_pos_err_m"] <= r["max_pos_err_m"] < 0.2
        assert r["time_tracking_s"] == pytest.approx(r["sim_time_s"])  # truth: always tracking
        assert len(r["trace_range_m"]) == len(r["trace_pos_err_m"]) > 0
    # A run of the table is exactly what a direct run_one gives.
    direct = run_one(build_specs(cfg, [2])[0])
    assert direct["delta_v_m_s"] == table.loc[2, "delta_v_m_s"]
    assert direct["contact_lateral_offset"] == table.loc[2, "contact_lateral_offset"]

    # Outputs: the resolved config, summary and plots.
    saved = load_config(out / "campaign.yaml", model=CampaignConfig)
    assert saved == cfg
    assert (out / "summary.json").is_file() and "Wilson 95%" in (out / "summary.txt").read_text()
    for name in ("contact_envelope.png", "delta_v_hist.png", "error_vs_range.png"):
        png = out / "plots" / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000

    # Resuming a complete campaign runs nothing; extending it runs only the new indices.
    again = run_campaign(cfg, out, serial=True, progress=False, plots=False)
    assert again.ran == [] and again.complete
    ext = run_campaign(CampaignConfig(**{**TINY, "runs": 5}), out, serial=True, progress=False, plots=False)
    assert ext.ran == [4] and list(ext.table["index"]) == [0, 1, 2, 3, 4]


def test_resume_refuses_a_different_campaign(tmp_path):
    cfg = CampaignConfig(**{**TINY, "runs": 1, "max_steps": 5})
    run_campaign(cfg, tmp_path, serial=True, progress=False, plots=False)
    other = CampaignConfig(**{**TINY, "runs": 1, "max_steps": 5, "seed": 99})
    with pytest.raises(ConfigError, match="different campaign .*seed"):
        run_campaign(other, tmp_path, serial=True, progress=False, plots=False)
    res = run_campaign(other, tmp_path, serial=True, progress=False, plots=False, fresh=True)
    assert res.ran == [0] and load_config(tmp_path / "campaign.yaml", model=CampaignConfig).seed == 99


def test_retry_errors_reruns_only_errored_runs(tmp_path, monkeypatch):
    import agents.controllers as ac

    cfg = CampaignConfig(**{**TINY, "runs": 2, "max_steps": 5, "controller": "flaky"})
    monkeypatch.setitem(ac.CONTROLLERS, "flaky", "agents.not_there_yet:Flaky")
    res = run_campaign(cfg, tmp_path, serial=True, progress=False, plots=False)
    assert res.complete and set(res.table["outcome"]) == {"error"} and res.summary["errors"] == 2
    monkeypatch.setitem(ac.CONTROLLERS, "flaky", "agents.glideslope:GlideslopeController")
    assert run_campaign(cfg, tmp_path, serial=True, progress=False, plots=False).ran == []
    res = run_campaign(cfg, tmp_path, serial=True, progress=False, plots=False, retry_errors=True)
    assert res.ran == [0, 1] and set(res.table["outcome"]) <= {"docked", "failed"}


# Three quick runs on truth perception (a few steps each).
QUICK = {**TINY, "perception": "truth", "runs": 3, "max_steps": 8}


@pytest.mark.parametrize("retry_errors", [False, True])
def test_a_damaged_part_is_quarantined_and_its_run_redone(tmp_path, caplog, retry_errors):
    cfg = CampaignConfig(**QUICK)
    ref = run_campaign(cfg, tmp_path / "ref", serial=True, progress=False, plots=False)
    out = tmp_path / "o"
    run_campaign(cfg, out, serial=True, progress=False, plots=False)
    bad = out / "parts" / "run_000001.parquet"
    damaged = bad.read_bytes()[:40]  # a part cut short (no Parquet footer)
    bad.write_bytes(damaged)
    res = run_campaign(cfg, out, serial=True, progress=False, plots=False,
                       retry_errors=retry_errors)
    assert res.ran == [1] and res.complete
    moved = out / "parts" / "quarantine" / "run_000001.parquet"
    assert moved.read_bytes() == damaged
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and str(bad) in warnings[0] and str(moved) in warnings[0]
    assert "\n" not in warnings[0]
    # The resumed campaign is the uninterrupted one.
    pd.testing.assert_frame_equal(frame(res.table), frame(ref.table))
    pd.testing.assert_frame_equal(frame(pd.read_parquet(out / "results.parquet")), frame(ref.table))
    # A part holding another run's row is damaged too; a second quarantine keeps the first.
    (out / "parts" / "run_000000.parquet").write_bytes(bad.read_bytes())
    bad.write_bytes(b"garbage")
    res = run_campaign(cfg, out, serial=True, progress=False, plots=False)
    assert res.ran == [0, 1]
    assert sorted(p.name for p in moved.parent.iterdir()) == [
        "run_000000.parquet", "run_000001.parquet", "run_000001.parquet.1"]
    pd.testing.assert_frame_equal(frame(res.table), frame(ref.table))


LOCKER = """
import sys, time
from agents.outputs import lock_folder
with lock_folder(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(60)
"""


def test_a_second_process_on_the_same_folder_is_refused(tmp_path):
    cfg = CampaignConfig(**{**QUICK, "runs": 1})
    out = tmp_path / "o"
    run_campaign(cfg, out, serial=True, progress=False, plots=False)
    before = sorted(p.name for p in (out / "parts").iterdir())
    other = subprocess.Popen([sys.executable, "-c", LOCKER, str(out)], stdout=subprocess.PIPE,
                             text=True)
    try:
        assert other.stdout.readline().strip() == "locked"
        for kw in ({}, {"fresh": True}, {"retry_errors": True}):
            busy = f"in use by another tridar-env process \\(pid {other.pid}\\)"
            with pytest.raises(ValueError, match=busy):
                run_campaign(CampaignConfig(**{**QUICK, "runs": 2}), out, serial=True,
                             progress=False, plots=False, **kw)
        assert sorted(p.name for p in (out / "parts").iterdir()) == before
    finally:
        other.kill()
        other.wait()
    assert run_campaign(CampaignConfig(**{**QUICK, "runs": 2}), out, serial=True, progress=False,
                        plots=False).ran == [1]


def test_resume_leaves_a_live_process_tmp_file_alone(tmp_path):
    cfg = CampaignConfig(**{**QUICK, "runs": 1})
    out = tmp_path / "o"
    run_campaign(cfg, out, serial=True, progress=False, plots=False)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        theirs = out / "parts" / f".run_000005.parquet.{live.pid}.tmp"
        stale = out / "parts" / f".run_000006.parquet.{dead_pid()}.tmp"
        theirs.write_bytes(b"being written")
        stale.write_bytes(b"partial")
        assert run_campaign(cfg, out, serial=True, progress=False, plots=False).ran == []
        assert theirs.read_bytes() == b"being written" and not stale.exists()
    finally:
        live.kill()
        live.wait()


def test_summary_success_rate_and_wilson_interval():
    rows = [{"outcome": "docked" if c == "docked" else "failed", "docked": c == "docked",
             "cause": c, "delta_v_m_s": dv}
            for c, dv in [("docked", 1.0), ("docked", 2.0), ("collision", 3.0), ("timeout", 4.0)]]
    rows.append({"outcome": "error", "docked": False, "cause": "RuntimeError: boom"})
    s = summarize(rows)
    assert s["runs"] == 5 and s["docked"] == 2 and s["success_rate"] == 0.4
    assert (s["wilson95_low"], s["wilson95_high"]) == wilson_interval(2, 5)
    assert s["causes"] == {"docked": 2, "collision": 1, "timeout": 1} and s["errors"] == 1
    assert s["delta_v_median_m_s"] == 2.5
    assert s["delta_v_mean_m_s"] == 2.5 and s["delta_v_p95_m_s"] == pytest.approx(3.85)
    assert np.isnan(s["track_losses_mean"])  # rows from before the column existed


# ---------------------------------------------------------------------------------------------
# Bad input: one error line, non-zero exit, nothing written
# ---------------------------------------------------------------------------------------------
# ``python -m agents.cli`` would register the subcommands on a second copy of the module.
CLI = [sys.executable, "-c", "import sys; from agents.cli import main; sys.exit(main())"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_fails_fast_and_writes_nothing(tmp_path):
    cfg = CampaignConfig(**TINY)
    out = tmp_path / "never"
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="cannot reach the Dask scheduler at 'tcp://127.0.0.1:"):
        run_campaign(cfg, out, scheduler=f"tcp://127.0.0.1:{_free_port()}", connect_timeout_s=2,
                     progress=False)
    assert time.perf_counter() - t0 < 15
    assert not out.exists()


@pytest.mark.parametrize(
    "content, words",
    [
        (None, "does not exist"),
        ("runs: [1, 2\n", "not valid YAML"),
        ("- 1\n- 2\n", "expected a mapping"),
        (yaml.safe_dump({**TINY, "runs": 0}), "runs: got 0"),
        (yaml.safe_dump({**TINY, "colour": "red"}), "colour: unknown key"),
        (yaml.safe_dump({**TINY, "controller": "pid"}), "controller='pid' is unknown"),
        (yaml.safe_dump({**TINY, "dispersions": {"env__initial__rnge_m": [1.0]}}), "rnge_m: unknown key"),
        (yaml.safe_dump({**TINY, "dispersions": {"env__initial__range_m": {"uniform": [-5, 1]}}}),
         "env.initial.range_m: got -"),
    ],
)
def test_cli_bad_campaign_yaml(tmp_path, capsys, content, words):
    path = tmp_path / "c.yaml"
    if content is not None:
        path.write_text(content)
    out = tmp_path / "out"
    assert main(["campaign", str(path), "--out", str(out), "--serial", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tridar-env campaign: error:") and words in err
    assert not out.exists()


def test_shipped_campaigns_validate():
    paths = sorted((CONFIG_DIR / "campaigns").glob("*.yaml"))
    assert len(paths) >= 3
    for p in paths:
        cfg = load_campaign(p)
        assert cfg.runs >= 10 and cfg.dispersions


def test_cli_campaign_prints_summary(tmp_path, capsys):
    path = write_yaml(tmp_path / "c.yaml", {**TINY, "runs": 2, "max_steps": 10})
    assert main(["campaign", str(path), "--out", str(tmp_path / "o"), "--serial", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "Wilson 95% interval" in text and "| runs " in text
    assert len(pd.read_parquet(tmp_path / "o" / "results.parquet")) == 2


@pytest.mark.slow
def test_cli_unreachable_scheduler_exit_code(tmp_path):
    path = write_yaml(tmp_path / "c.yaml", TINY)
    proc = subprocess.run(
        [*CLI, "campaign", str(path), "--out", str(tmp_path / "o"),
         "--scheduler", f"tcp://127.0.0.1:{_free_port()}"],
        check=False, capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "cannot reach the Dask scheduler" in proc.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_cli_campaign_killed_then_resumed(tmp_path):
    """A real interruption: SIGINT to the CLI mid-campaign, then the same command again."""
    # Runs of ~0.3 s each (25-30 m approaches on truth+noise), enough that the campaign cannot
    # finish between the second part landing and the interrupt.
    n = 12
    path = write_yaml(tmp_path / "c.yaml", {
        **TINY, "runs": n, "max_steps": 3000,
        "dispersions": {**TINY["dispersions"], "env__initial__range_m": {"uniform": [25.0, 30.0]}},
    })
    out = tmp_path / "o"
    cmd = [*CLI, "campaign", str(path), "--out", str(out),
           "--workers", "2", "--no-progress", "--no-plots"]
    # A job started in the background by a non-interactive shell (CI runners, `cmd &`) inherits
    # SIGINT ignored, and Python then installs no KeyboardInterrupt handler: the CLI would ignore
    # the interrupt and finish every run. Give it Ctrl-C's default disposition, as in a terminal.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 90
    while time.time() < deadline and len(list((out / "parts").glob("run_*.parquet"))) < 2:
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    done_before = {p.name for p in (out / "parts").glob("run_*.parquet")}
    assert 2 <= len(done_before) < n
    assert subprocess.run(cmd, check=False, capture_output=True, timeout=300).returncode == 0
    table = pd.read_parquet(out / "results.parquet")
    assert list(table["index"]) == list(range(n))
    serial = run_campaign(load_campaign(path), tmp_path / "ref", serial=True, progress=False, plots=False)
    pd.testing.assert_frame_equal(frame(table), frame(serial.table))


@pytest.mark.slow
def test_campaign_on_an_existing_scheduler(tmp_path):
    """--scheduler: the same rows on a cluster the campaign did not start."""
    from dask.distributed import LocalCluster

    cfg = CampaignConfig(**{**TINY, "runs": 3, "max_steps": 30})
    ref = run_campaign(cfg, tmp_path / "serial", serial=True, progress=False, plots=False)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        res = run_campaign(cfg, tmp_path / "remote", scheduler=c.scheduler_address, progress=False,
                           plots=False)
        assert c.scheduler_address.startswith("tcp://")
    pd.testing.assert_frame_equal(frame(res.table), frame(ref.table))
