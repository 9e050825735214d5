"""``tridar-env bench soak``: the checkpoint table and its verdict, on tiny step counts."""

from __future__ import annotations

import argparse
import re

import pytest

from agents.benchmarks.soak import Checkpoint, _count, growth_pct, rss_mib, soak, verdict
from agents.cli import main


def test_checkpoints_hold_steps_memory_growth_and_rate() -> None:
    probe = iter([100.0, 101.0, 110.0, 104.0])
    calls = []

    def step() -> int:
        calls.append(1)
        return 3  # a batched env: several steps per call

    rows = soak("fake", step, total=20, checkpoints=4, memory=lambda: next(probe))
    assert [r.steps for r in rows] == [6, 12, 15, 21]  # first multiple of 3 past 5, 10, 15, 20
    assert sum(calls) * 3 == rows[-1].steps
    assert [r.rss_mib for r in rows] == [100.0, 101.0, 110.0, 104.0]
    assert [r.growth_pct for r in rows] == pytest.approx([0.0, 1.0, 10.0, 4.0])
    assert all(r.steps_per_s > 0 for r in rows)
    ok, line = verdict(rows)
    assert not ok and line.startswith("verdict: FAIL") and "+10.0 %" in line
    ok, line = verdict([*rows[:2], Checkpoint("other", 5, 50.0, 0.0, 1.0)])
    assert ok and "fake +1.0 %" in line and "other +0.0 %" in line
    # Fewer steps than checkpoints: one row per step, never an empty table.
    assert [r.steps for r in soak("few", lambda: 1, total=2, checkpoints=10, memory=lambda: 1.0)] == [1, 2]


def test_growth_and_rss() -> None:
    assert growth_pct(105.0, 100.0) == pytest.approx(5.0)
    assert growth_pct(95.0, 100.0) == pytest.approx(-5.0)
    assert 1.0 < rss_mib() < 1e6


@pytest.mark.parametrize("text, value", [("1e6", 1_000_000), ("64", 64), ("1", 1)])
def test_step_counts_parse(text: str, value: int) -> None:
    assert _count(text) == value


@pytest.mark.parametrize("text", ["0", "-5", "1.5", "nan", "inf", "lots"])
def test_bad_step_counts_are_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        _count(text)


def test_cli_soak_prints_a_sane_table(capsys) -> None:
    code = main(["bench", "soak", "--truth-steps", "640", "--tridar-steps", "6", "--checkpoints",
                 "3", "--envs", "64", "--no-progress"])
    out = capsys.readouterr().out
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in out.splitlines()
            if ln.startswith("| ") and "phase" not in ln]
    assert len(rows) == 6, out
    for phase in ("truth (64 batched)", "tridar"):
        mine = [r for r in rows if r[0] == phase]
        steps = [int(r[1]) for r in mine]
        rss = [float(r[2]) for r in mine]
        growth = [float(r[3]) for r in mine]
        assert steps == sorted(steps) and steps[-1] == (640 if phase.startswith("truth") else 6)
        assert all(x > 0 for x in rss) and all(float(r[4]) > 0 for r in mine)
        assert growth[0] == 0.0
        for g, x in zip(growth, rss):  # the printed growth is the printed RSS over the first
            assert g == pytest.approx(100 * (x - rss[0]) / rss[0], abs=0.1)
    line = out.strip().splitlines()[-1]
    assert re.match(r"verdict: (PASS|FAIL): largest RSS growth after warm-up", line)
    assert code == (0 if "PASS" in line else 1)
