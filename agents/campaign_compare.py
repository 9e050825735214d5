"""Campaigns side by side: the same dispersed runs flown with two sensors (or controllers, or
code versions), compared run for run.

A trade between sensors is only fair on the same runs: :func:`compare` checks that the
campaigns are paired (the same mission, seed and dispersions, so run ``i`` has the same initial
state, target motion and faults in each) and counts the runs on which they disagree, next to
each campaign's docked fraction (Wilson 95 %), valid-but-wrong steps, pose error binned by range
to the target and cost per step. Folders are only read, never written: a campaign still running
is compared on the runs it has finished.

``tridar-env compare DIR DIR [...]`` prints the three tables; ``--plot FILE`` draws the error
against range.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Comparison", "compare", "plot_error_vs_range", "read_campaign"]

#: Range bins [m] of the error-versus-range table (to the target origin, as the run traces).
DEFAULT_BINS = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0)


@dataclass(frozen=True)
class CampaignRuns:
    """One campaign folder: its label, its saved spec (``campaign.yaml``) and its run rows."""

    label: str
    folder: Path
    spec: dict[str, Any]
    table: Any  # pandas.DataFrame, one row per finished run


def read_campaign(folder: str | Path, label: str | None = None) -> CampaignRuns:
    """The finished runs of a campaign folder (``results.parquet``, or the part files of one
    still running); ValueError naming the folder when it holds no campaign."""
    import pandas as pd
    import yaml

    folder = Path(folder)
    spec_path = folder / "campaign.yaml"
    if not spec_path.is_file():
        raise ValueError(f"{folder}: no campaign.yaml; expected a folder `tridar-env campaign` wrote")
    with spec_path.open(encoding="utf-8") as fh:
        spec = yaml.safe_load(fh) or {}
    if not isinstance(spec, dict):
        raise ValueError(  # noqa: TRY004  (a file's content, reported as bad input)
            f"{spec_path}: expected a mapping, got {type(spec).__name__}")
    parts = sorted((folder / "parts").glob("run_*.parquet")) if (folder / "parts").is_dir() else []
    if parts:
        frames = []
        for p in parts:
            try:
                frames.append(pd.read_parquet(p))
            except Exception as exc:  # noqa: BLE001  (pyarrow raises many types for a damaged file)
                raise ValueError(f"{p}: cannot be read ({str(exc).splitlines()[0]})") from None
        table = pd.concat(frames, ignore_index=True)
    elif (folder / "results.parquet").is_file():
        table = pd.read_parquet(folder / "results.parquet")
    else:
        raise ValueError(f"{folder}: no finished runs (no parts/ and no results.parquet)")
    table = table.sort_values("index", kind="stable").reset_index(drop=True)
    return CampaignRuns(label or folder.name, folder, spec, table)


def _identity(spec: dict[str, Any]) -> dict[str, Any]:
    """What makes run ``i`` the same run in two campaigns (not the perception or controller)."""
    return {k: spec.get(k) for k in ("env_id", "mission", "seed", "dispersions", "max_steps")}


@dataclass(frozen=True)
class Comparison:
    """The tables of :func:`compare` (lists of row dicts) and whether the campaigns are paired."""

    paired: bool
    common_runs: int
    summary: list[dict[str, Any]]
    by_range: list[dict[str, Any]]
    pairs: list[dict[str, Any]]

    def format(self) -> str:
        from agents.benchmarks.timing import format_table

        head = (f"paired: {'yes' if self.paired else 'NO (different missions, seeds or dispersions)'}"
                f"; runs finished in every campaign: {self.common_runs}")
        caption = "pose error against range to the target (all trace samples of the common runs in the bin)"
        parts = [head, format_table(self.summary), caption, format_table(self.by_range)]
        if self.pairs:
            parts += ["run for run (common runs)", format_table(self.pairs)]
        return "\n\n".join(parts)


def _stat(a: np.ndarray, fn: Any) -> float:
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(fn(a)) if a.size else float("nan")


def compare(campaigns: Sequence[CampaignRuns], bins: Sequence[float] = DEFAULT_BINS) -> Comparison:
    """Compare campaigns on the runs every one of them finished (module docstring).

    Args:
        campaigns: two or more campaigns (:func:`read_campaign`).
        bins: increasing range bin edges [m] of the error table.
    """
    from agents.episode import wilson_interval

    if len(campaigns) < 2:
        raise ValueError(f"{len(campaigns)} campaign(s); expected at least 2 to compare")
    edges = np.asarray(bins, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bins={list(bins)}; expected at least 2 increasing finite edges [m]")
    ids = [set(c.table["index"].astype(int)) for c in campaigns]
    common = sorted(set.intersection(*ids))
    first = _identity(campaigns[0].spec)
    paired = all(_identity(c.spec) == first for c in campaigns[1:])
    if paired and common:
        seeds = [c.table.set_index("index").loc[common, "env_seed"].to_numpy() for c in campaigns]
        paired = all(np.array_equal(seeds[0], s) for s in seeds[1:])
    tables = [c.table[c.table["index"].isin(common)].sort_values("index") for c in campaigns]

    summary, by_range = [], []
    for c, t in zip(campaigns, tables):
        n, k = len(t), int(t["docked"].astype(bool).sum())
        lo, hi = wilson_interval(k, n)
        per_step = t["wall_time_s"].to_numpy(float) / np.maximum(t["steps"].to_numpy(float), 1.0)
        summary.append({
            "campaign": c.label, "perception": c.spec.get("perception", "?"),
            "controller": c.spec.get("controller", "?"), "runs": n, "docked": k,
            "docked %": f"{k / n:.1%}" if n else "-", "Wilson 95%": f"[{lo:.1%}, {hi:.1%}]",
            "valid-but-wrong steps": int(t["hmi_steps"].sum()),
            "RMS pos err, median run [mm]": 1e3 * _stat(t["rms_pos_err_m"], np.median),
            "max pos err, p95 run [mm]": 1e3 * _stat(t["max_pos_err_m"], lambda a: np.percentile(a, 95)),
            "RMS att err, median run [deg]": _stat(t["rms_att_err_deg"], np.median),
            "delta-v median [m/s]": _stat(t["delta_v_m_s"], np.median),
            "wall per step, median run [ms]": 1e3 * _stat(per_step, np.median),
        })
        r = np.concatenate([np.asarray(v, float) for v in t["trace_range_m"]]) if n else np.zeros(0)
        e = np.concatenate([np.asarray(v, float) for v in t["trace_pos_err_m"]]) if n else np.zeros(0)
        a = np.concatenate([np.asarray(v, float) for v in t["trace_att_err_deg"]]) if n else np.zeros(0)
        for lo_m, hi_m in pairwise(edges):
            m = (r >= lo_m) & (r < hi_m) & np.isfinite(e)
            by_range.append({
                "campaign": c.label, "range [m]": f"{lo_m:g}-{hi_m:g}", "samples": int(m.sum()),
                "pos RMS [mm]": 1e3 * _stat(e[m], lambda x: np.sqrt(np.mean(x**2))),
                "pos max [mm]": 1e3 * _stat(e[m], np.max),
                "att RMS [deg]": _stat(a[m], lambda x: np.sqrt(np.mean(x**2))),
                "att max [deg]": _stat(a[m], np.max),
            })
    pairs = []
    if paired and common:
        base = tables[0]["docked"].astype(bool).to_numpy()
        for c, t in zip(campaigns[1:], tables[1:]):
            other = t["docked"].astype(bool).to_numpy()
            pairs.append({
                "pair": f"{campaigns[0].label} vs {c.label}", "both docked": int(np.sum(base & other)),
                f"only {campaigns[0].label}": int(np.sum(base & ~other)),
                f"only {c.label}": int(np.sum(~base & other)), "neither": int(np.sum(~base & ~other)),
            })
    return Comparison(paired, len(common), summary, by_range, pairs)


def plot_error_vs_range(campaigns: Sequence[CampaignRuns], path: str | Path) -> Path:
    """Position error against range for each campaign (every trace sample, log scale), to a new
    PNG ``path`` (an existing file is refused, never overwritten)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"--plot {path}: expected a .png file name")
    if path.exists():
        raise ValueError(f"--plot {path}: exists; expected a new file (nothing is overwritten)")
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for c in campaigns:
        t = c.table
        r = np.concatenate([np.asarray(v, float) for v in t["trace_range_m"]])
        e = np.concatenate([np.asarray(v, float) for v in t["trace_pos_err_m"]])
        ok = np.isfinite(r) & np.isfinite(e) & (e > 0)
        ax.scatter(r[ok], 1e3 * e[ok], s=2, alpha=0.3, label=f"{c.label} ({len(t)} runs)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("range to the target [m]")
    ax.set_ylabel("published position error [mm]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(markerscale=4)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
