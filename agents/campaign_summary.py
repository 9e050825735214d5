"""What a table of run rows says: the summary (success rate with a Wilson interval, causes,
delta-v, contact and estimation figures), its text table, and a campaign's plots.

The same for campaigns and ``evaluate``; rows are those of :func:`agents.runner.run_one`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PLOT_FILES", "format_summary", "plot_campaign", "summarize"]

#: The PNG files :func:`plot_campaign` writes.
PLOT_FILES = ("contact_envelope.png", "delta_v_hist.png", "error_vs_range.png")


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------
def summarize(df: Any) -> dict[str, Any]:
    """Success rate with a Wilson 95% interval, causes and distributions of the main figures.

    Runs that crashed (outcome ``error``) count as runs that did not dock, and are reported
    separately from the termination causes.

    Args:
        df: a results table (``pandas.DataFrame``) or a list of row dicts.
    """
    import pandas as pd

    from agents.episode import wilson_interval

    df = pd.DataFrame(df) if not isinstance(df, pd.DataFrame) else df
    n = len(df)
    docked = int(df["docked"].sum()) if n else 0
    # Success: docked, or a fly-around completed (rows written before "success" existed: docked).
    k = int(df["success"].fillna(df["docked"]).astype(bool).sum()) if n and "success" in df else docked
    lo, hi = wilson_interval(k, n)
    errored = (df["outcome"] == "error") if n and "outcome" in df else None
    causes = df.loc[~errored, "cause"].value_counts().to_dict() if errored is not None else {}

    def stat(col: str, fn: Callable[[np.ndarray], float], mask: Any = None) -> float:
        if col not in df:
            return float("nan")
        s = df[col] if mask is None else df.loc[mask, col]
        a = pd.to_numeric(s, errors="coerce").to_numpy(dtype=np.float64)
        a = a[np.isfinite(a)]
        return float(fn(a)) if a.size else float("nan")

    med = np.median
    p90 = lambda a: np.percentile(a, 90)
    contact = df["cause"].isin(["docked", "collision"]) if n else None
    return {
        "runs": n,
        "docked": docked,
        "succeeded": k,
        "success_rate": k / n if n else float("nan"),
        "wilson95_low": lo,
        "wilson95_high": hi,
        "causes": {str(c): int(v) for c, v in causes.items()},
        "errors": int(errored.sum()) if errored is not None else 0,
        "delta_v_median_m_s": stat("delta_v_m_s", med),
        "delta_v_p90_m_s": stat("delta_v_m_s", p90),
        "delta_v_mean_m_s": stat("delta_v_m_s", np.mean),
        "delta_v_p95_m_s": stat("delta_v_m_s", lambda a: np.percentile(a, 95)),
        "contact_closing_speed_median_m_s": stat("contact_closing_speed", med, contact),
        "contact_lateral_offset_p90_m": stat("contact_lateral_offset", p90, contact),
        "max_pos_err_median_m": stat("max_pos_err_m", med),
        "rms_pos_err_median_m": stat("rms_pos_err_m", med),
        "rms_att_err_median_deg": stat("rms_att_err_deg", med),
        "acquisitions_mean": stat("acquisitions", np.mean),
        "track_losses_mean": stat("track_losses", np.mean),
        "symmetry_switches_total": stat("symmetry_switches", np.sum),
        "sim_time_median_s": stat("sim_time_s", med),
        "pose_fraction_mean": stat("pose_fraction", np.mean),
        "pose_fraction_min": stat("pose_fraction", np.min),
        "hmi_steps_total": stat("hmi_steps", np.sum),
        "restarts_total": stat("restarts", np.sum),
        "restarts_reacquired_total": stat("restarts_reacquired", np.sum),
        "restarts_pending_total": stat("restarts_pending", np.sum),
    }


def format_summary(summary: dict[str, Any], title: str | None = None) -> str:
    """The summary as a two-column text table (the same for campaigns and ``evaluate``)."""
    from agents.benchmarks.timing import format_table

    s = summary
    causes = ", ".join(f"{c} {v}" for c, v in sorted(s["causes"].items())) or "-"
    rows = [
        ("runs", s["runs"]),
        ("docked", s["docked"]),
        ("succeeded (docked or fly-around completed)", s.get("succeeded", s["docked"])),
        ("success rate", f"{s['success_rate']:.1%}" if s["runs"] else "-"),
        ("Wilson 95% interval", f"[{s['wilson95_low']:.1%}, {s['wilson95_high']:.1%}]"),
        ("causes", causes),
        ("errored runs", s["errors"]),
        ("delta-v median / p90 [m/s]", f"{s['delta_v_median_m_s']:.3g} / {s['delta_v_p90_m_s']:.3g}"),
        ("delta-v mean / p95 [m/s]", f"{s['delta_v_mean_m_s']:.3g} / {s['delta_v_p95_m_s']:.3g}"),
        ("closing speed at contact, median [m/s]", f"{s['contact_closing_speed_median_m_s']:.3g}"),
        ("lateral offset at contact, p90 [m]", f"{s['contact_lateral_offset_p90_m']:.3g}"),
        ("max position error, median [m]", f"{s['max_pos_err_median_m']:.3g}"),
        ("RMS position error, median [m]", f"{s['rms_pos_err_median_m']:.3g}"),
        ("RMS attitude error, median [deg]", f"{s['rms_att_err_median_deg']:.3g}"),
        ("acquisitions per run, mean", f"{s['acquisitions_mean']:.3g}"),
        ("losses of track per run, mean", f"{s['track_losses_mean']:.3g}"),
        ("switches to a near-symmetric twin, total", f"{s['symmetry_switches_total']:.0f}"),
        ("sim time, median [s]", f"{s['sim_time_median_s']:.4g}"),
        ("pose available, mean / worst run", (f"{s.get('pose_fraction_mean', np.nan):.2%} / "
                                              f"{s.get('pose_fraction_min', np.nan):.2%}")),
        ("valid-but-wrong steps (error > PL), total", f"{s.get('hmi_steps_total', np.nan):.0f}"),
        ("planned restarts / reacquired / pending at the end, total", (
            f"{s.get('restarts_total', np.nan):.0f} / {s.get('restarts_reacquired_total', np.nan):.0f}"
            f" / {s.get('restarts_pending_total', np.nan):.0f}")),
    ]
    table = format_table([{"metric": m, "value": v} for m, v in rows])
    return f"{title}\n{table}" if title else table


# ---------------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------------
_COLORS = {"docked": "tab:green", "collision": "tab:red"}


def plot_campaign(df: Any, envelope: Any, out_dir: str | Path) -> list[Path]:
    """PNG plots: contact conditions against the envelope, delta-v histogram, error vs range.

    Args:
        df: results table.
        envelope: :class:`perception.config.DockingEnvelopeConfig` to draw.
        out_dir: folder for the PNG files.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import FormatStrFormatter

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []

    # 1. Contact conditions against the envelope.
    fig = Figure(figsize=(10, 4.5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    contact = df[df["cause"].isin(["docked", "collision"])] if "contact_lateral_offset" in df else df.iloc[:0]
    e = envelope
    ax1.add_patch(Rectangle(
        (e.axial_speed_min_m_s, 0.0), e.axial_speed_max_m_s - e.axial_speed_min_m_s,
        e.lateral_offset_max_m, fill=False, ec="k", ls="--", label="envelope",
    ))
    ax2.add_patch(Rectangle(
        (0.0, 0.0), e.lateral_speed_max_m_s, e.misalignment_max_deg, fill=False, ec="k", ls="--",
        label="envelope",
    ))
    for cause, grp in contact.groupby("cause") if len(contact) else []:
        c = _COLORS.get(cause, "tab:gray")
        ax1.scatter(grp["contact_closing_speed"], grp["contact_lateral_offset"], s=14, c=c, label=cause)
        ax2.scatter(grp["contact_lateral_speed"], grp["contact_misalignment_deg"], s=14, c=c, label=cause)
    ax1.set(xlabel="closing speed at contact [m/s]", ylabel="lateral offset [m]",
            title=f"contact conditions ({len(contact)} of {len(df)} runs reached contact)")
    ax2.set(xlabel="lateral speed at contact [m/s]", ylabel="misalignment [deg]")
    for ax in (ax1, ax2):
        ax.autoscale_view()
        ax.set_xlim(left=0.0)
        ax.set_ylim(bottom=0.0)
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    paths.append(out / PLOT_FILES[0])
    fig.savefig(paths[-1], dpi=110)

    # 2. Delta-v histogram by outcome.
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    ok = df[np.isfinite(df["delta_v_m_s"].astype(float))] if "delta_v_m_s" in df else df.iloc[:0]
    if len(ok):
        groups = [(c, g["delta_v_m_s"].to_numpy(float)) for c, g in ok.groupby("cause")]
        bins = np.histogram_bin_edges(ok["delta_v_m_s"].to_numpy(float), bins="auto")
        ax.hist([g for _, g in groups], bins=bins, stacked=True, label=[c for c, _ in groups],
                color=[_COLORS.get(c, None) for c, _ in groups] if all(c in _COLORS for c, _ in groups) else None)
        ax.legend(fontsize=8)
    ax.set(xlabel="delta-v [m/s]", ylabel="runs", title="delta-v per run")
    ax.grid(alpha=0.3)
    paths.append(out / PLOT_FILES[1])
    fig.savefig(paths[-1], dpi=110)

    # 3. Estimation error against range (all runs' valid-pose steps).
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    r = np.concatenate([np.asarray(v, float) for v in df.get("trace_range_m", [])] or [np.empty(0)])
    pe = np.concatenate([np.asarray(v, float) for v in df.get("trace_pos_err_m", [])] or [np.empty(0)])
    good = np.isfinite(r) & np.isfinite(pe) & (r > 0)
    r, pe = r[good], pe[good]
    if r.size:
        ax.scatter(r, pe, s=3, alpha=0.3, c="tab:blue", label="steps")
        edges = np.geomspace(max(r.min(), 1e-2), r.max() * 1.0001, 12)
        which = np.digitize(r, edges)
        centres, med_, p90_ = [], [], []
        for b in range(1, len(edges)):
            sel = pe[which == b]
            if sel.size:
                centres.append(np.sqrt(edges[b - 1] * edges[b]))
                med_.append(np.median(sel))
                p90_.append(np.percentile(sel, 90))
        ax.plot(centres, med_, "k-o", ms=3, label="median")
        ax.plot(centres, p90_, "k--", label="p90")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
        ax.tick_params(axis="x", which="minor", labelsize=7)
        ax.legend(fontsize=8)
    ax.set(xlabel="range [m]", ylabel="position error [m]", title="estimation error vs range")
    ax.grid(alpha=0.3, which="both")
    paths.append(out / PLOT_FILES[2])
    fig.savefig(paths[-1], dpi=110)
    return paths
