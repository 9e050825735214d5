"""Integrity of the published state vector in closed loop, on the library and on generated shapes.

Long module: one benchmark's cases, per-frame record, summary statistics (NEES bands over
correlated frames), tables, files and plot, each used only here.

What a navigation sensor promises is not a small error but an error inside the bound it publishes
(DESIGN.md, "Integrity"). The glideslope controller flies the stock ``final_approach`` mission on
the full TriDAR pipeline (``perception="tridar"``) against each target: the library's ``cubesat``,
``cygnss`` and ``iss_port`` (``hubble`` with ``--all``) and one generated shape of every kind in
:data:`perception.shapes.SHAPE_KINDS` (seed :data:`SHAPE_SEED`, fixed before any result was seen),
written as an STL file and flown through the file path with its port given as a user would
(``target__name``, ``target__port_position_m``, ``target__port_axis``). Everything else is the
stock mission.

Per frame with a pose (``valid.position``; the pipeline publishes position and attitude
together) it compares the docking port position ``p + R r_port`` with the truth's and records the
protection level (PL), alert limit (AL) and the degraded flag:

* **HMI** (hazardously misleading): a valid pose (``valid.pose``: not degraded) whose port error
  exceeds its PL;
* **MI** (misleading): any published pose, degraded or not, whose port error exceeds its PL;
* **NEES** of the port position (3 dof, from :func:`perception.pipeline.integrity.port_covariance` of the
  published covariance) and of the attitude (3 dof, block ``[6:9, 6:9]``, rotation-vector error).
  The 95 % band printed is that of a mean of ``n_eff`` independent chi-square(3) values
  (``chi2_{3 n_eff}.ppf / n_eff``), where ``n_eff`` counts each run's frames divided by the
  integrated autocorrelation time of its NEES series (:func:`effective_count`): successive frames
  of a track are strongly correlated, and a band over every frame as if independent is far too
  narrow. The range table splits the position's NEES along the line of sight to the port (1 dof)
  and across it (2 dof; :func:`los_split`): the time of flight's range offset and the shapes'
  lateral offsets are different errors, and a mean of 3 can hide one direction 5x too
  pessimistic under another too confident.

Goals (issue 16): docked >= 95 % on every shape; HMI <= 1e-4 of frames and none with a port error
> 0.1 m; mean NEES inside its band. Writes ``rows.csv``, ``rows.json`` and ``error_vs_pl.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Library targets flown by default (``hubble`` joins with ``--all``).
LIBRARY_TARGETS = ("cubesat", "cygnss", "iss_port")
#: Seed of every generated shape (chosen once, before any run; never tuned on).
SHAPE_SEED = 2026
#: Numerical slack on "error > PL" [m]: a truth observer publishes PL 0 with an error of round-off.
ERROR_SLACK_M = 1e-9
#: Chi-square(3) mean of an honest 3-dof NEES.
NEES_DOF = 3
#: Sensor-to-port range bins of the by-range breakdown [m].
RANGE_BINS_M = ((0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, math.inf))

__all__ = [
    "LIBRARY_TARGETS", "RANGE_BINS_M", "SHAPE_SEED", "RunRecord", "TargetCase",
    "autocorrelation_time", "by_range", "display_row", "effective_count", "file_case", "fly",
    "generated_case", "library_case", "los_split", "make_case_env", "nees", "nees_band", "new_folder",
    "plot_error_vs_pl", "summarise", "wilson_interval", "write_rows",
]


# --------------------------------------------------------------------------- targets
@dataclass(frozen=True)
class TargetCase:
    """One target of the benchmark: a label and the mission overrides that fly it."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)


def library_case(name: str) -> TargetCase:
    """A library target (``perception.targets.LIBRARY``) on the stock mission."""
    return TargetCase(name, {"target__name": name})


def file_case(label: str, path: str | Path, port_position: Sequence[float], port_axis: Sequence[float],
              scale: float | None = None) -> TargetCase:
    """A user's mesh file with its port, flown through the config as a user would."""
    ov: dict[str, Any] = {
        "target__name": str(path),
        "target__port_position_m": [float(v) for v in port_position],
        "target__port_axis": [float(v) for v in port_axis],
    }
    if scale is not None:
        ov["target__scale"] = float(scale)
    return TargetCase(label, ov)


def generated_case(kind: str, seed: int, folder: str | Path) -> TargetCase:
    """Write generated shape ``kind`` (``seed``) as ``folder/<kind>_<seed>.stl`` and fly the file."""
    from perception.shapes import save_generated

    path = Path(folder) / f"{kind}_{seed}.stl"
    pos, axis = save_generated(kind, seed, path)
    return file_case(f"{kind}:{seed}", path, pos, axis)


def make_case_env(case: TargetCase, perception: str = "tridar", **overrides: Any) -> Any:
    """``TriDAR/FinalApproach-v0`` (stock ``final_approach``) with the case's target."""
    from agents.campaign import make_env

    return make_env("TriDAR/FinalApproach-v0", perception, {**case.overrides, **overrides})


# --------------------------------------------------------------------------- one run
@dataclass
class RunRecord:
    """One closed-loop approach and its per-frame integrity figures.

    Per-frame arrays hold the frames with a published pose only (``valid.position``).

    Attributes:
        label: target label.
        seed: reset seed.
        outcome: ``docked``, a termination cause or ``timeout``.
        steps: env steps flown.
        wall_s: wall time of the run [s].
        range_m: (F,) true sensor-to-port distance [m].
        port_err_m: (F,) port position error [m].
        att_err_rad: (F,) attitude error [rad].
        pl_m, al_m: (F,) protection level and alert limit [m].
        degraded: (F,) bool, published degraded.
        nees_pos, nees_att: (F,) NEES of the port position and the attitude (NaN where the
            published covariance is singular, e.g. a noise-free truth observer).
        nees_los, nees_across: (F,) the port position's NEES along the line of sight to it
            (1 dof) and across it (2 dof), each on its own marginal (:func:`los_split`);
            NaN where not recorded.
    """

    label: str
    seed: int
    outcome: str
    steps: int
    wall_s: float
    range_m: FloatArray
    port_err_m: FloatArray
    att_err_rad: FloatArray
    pl_m: FloatArray
    al_m: FloatArray
    degraded: npt.NDArray[np.bool_]
    nees_pos: FloatArray
    nees_att: FloatArray
    nees_los: FloatArray | None = None
    nees_across: FloatArray | None = None

    def __post_init__(self) -> None:
        for k in ("nees_los", "nees_across"):
            if getattr(self, k) is None:
                setattr(self, k, np.full(self.nees_pos.shape, np.nan))

    @property
    def docked(self) -> bool:
        return self.outcome == "docked"

    @property
    def frames(self) -> int:
        return int(self.port_err_m.size)

    @property
    def misleading(self) -> npt.NDArray[np.bool_]:
        """(F,) published poses whose port error exceeds the protection level."""
        return self.port_err_m > self.pl_m + ERROR_SLACK_M

    @property
    def hazardous(self) -> npt.NDArray[np.bool_]:
        """(F,) valid (not degraded) poses whose port error exceeds the protection level."""
        return self.misleading & ~self.degraded

    def summary(self) -> dict[str, Any]:
        """Counts and maxima of this run (for campaign tables)."""
        ok = ~self.degraded
        return {
            "label": self.label, "seed": self.seed, "outcome": self.outcome, "steps": self.steps,
            "frames": self.frames, "degraded": int(self.degraded.sum()),
            "hmi": int(self.hazardous.sum()), "mi": int(self.misleading.sum()),
            "max_port_err_valid_m": float(self.port_err_m[ok].max()) if ok.any() else math.nan,
            "max_att_err_valid_deg": float(np.degrees(self.att_err_rad[ok].max())) if ok.any() else math.nan,
            "max_port_err_m": float(self.port_err_m.max()) if self.frames else math.nan,
            "wall_s": self.wall_s,
        }


def nees(error: FloatArray, cov: FloatArray) -> float:
    """``e^T C^-1 e``; NaN when ``C`` is not positive definite (nothing to normalise by)."""
    C = 0.5 * (cov + cov.T)
    lam, V = np.linalg.eigh(C)
    if not (lam[0] > 1e-300 * max(lam[-1], 1.0)) or not np.all(np.isfinite(lam)):
        return math.nan
    y = V.T @ error
    return float(np.sum(y * y / lam))


def los_split(error: FloatArray, cov: FloatArray, port: FloatArray) -> tuple[float, float]:
    """The NEES of a position ``error`` (3,) under ``cov`` (3, 3) along the line of sight to
    ``port`` (3,; sensor frame) and across it, each on its marginal (1 and 2 dof: means 1 and 2
    when honest). NaN where that marginal is not positive definite."""
    from perception.geometry import los_basis

    u, *across = los_basis(np.asarray(port, dtype=np.float64))
    B = np.stack(across)
    C = 0.5 * (cov + cov.T)
    return nees(np.array([u @ error]), np.array([[u @ C @ u]])), nees(B @ error, B @ C @ B.T)


def fly(env: Any, seed: int, controller: str = "glideslope", max_steps: int | None = None,
        on_step: Callable[[], None] | None = None) -> RunRecord:
    """Fly one approach with ``controller`` on ``env`` and record the integrity of every pose.

    Args:
        env: a ``DockingEnv`` (possibly wrapped), e.g. from :func:`make_case_env`.
        seed: reset seed (the run is a function of it).
        controller: a name for :func:`agents.controllers.make_controller`.
        max_steps: stop (outcome ``timeout``) after this many steps.
        on_step: called after every step (progress bars).
    """
    from scipy.spatial.transform import Rotation

    from agents.controllers import make_controller
    from perception.geometry import fast_quat_to_matrix
    from perception.pipeline.integrity import port_covariance

    base = env.unwrapped
    policy = make_controller(controller, base.cfg)
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()
    r_port = np.asarray(base.target.T_target_port[:3, 3], dtype=np.float64)
    cols: dict[str, list[float]] = {k: [] for k in (
        "range", "err", "att", "pl", "al", "deg", "nees_p", "nees_a", "nees_l", "nees_x")}
    t0 = time.perf_counter()
    obs, info = env.reset(seed=int(seed))
    steps, outcome = 0, "timeout"
    while True:
        obs, _, terminated, truncated, info = env.step(np.asarray(policy(obs), dtype=np.float32))
        steps += 1
        sv = base.state_vector
        if sv is not None and sv.valid.position:
            T = info["truth_T_sensor_target"]
            R_est = fast_quat_to_matrix(sv.quaternion)
            port_true = T[:3, :3] @ r_port + T[:3, 3]
            e = sv.position + R_est @ r_port - port_true
            th = Rotation.from_matrix(T[:3, :3] @ R_est.T).as_rotvec()
            C = sv.covariance
            cols["range"].append(math.sqrt(float(port_true @ port_true)))
            cols["err"].append(math.sqrt(float(e @ e)))
            cols["att"].append(math.sqrt(float(th @ th)))
            cols["pl"].append(sv.protection_level)
            cols["al"].append(sv.alert_limit)
            cols["deg"].append(bool(sv.valid.degraded))
            Cp = port_covariance(C, R_est, r_port)
            cols["nees_p"].append(nees(e, Cp))
            n_l, n_x = los_split(e, Cp, sv.position + R_est @ r_port)
            cols["nees_l"].append(n_l)
            cols["nees_x"].append(n_x)
            cols["nees_a"].append(nees(th, C[6:9, 6:9]))
        if on_step is not None:
            on_step()
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            outcome = info["termination"] if terminated else "timeout"
            break
    a = {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}
    return RunRecord(
        label=str(getattr(base.target, "name", "")), seed=int(seed), outcome=outcome, steps=steps,
        wall_s=time.perf_counter() - t0, range_m=a["range"], port_err_m=a["err"],
        att_err_rad=a["att"], pl_m=a["pl"], al_m=a["al"], degraded=a["deg"].astype(bool),
        nees_pos=a["nees_p"], nees_att=a["nees_a"], nees_los=a["nees_l"], nees_across=a["nees_x"],
    )


# --------------------------------------------------------------------------- summary math
def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """Wilson score 95 % interval of a binomial proportion (``agents.episode.wilson_interval``)."""
    from agents.episode import wilson_interval as _wilson

    return _wilson(successes, n)


def nees_band(n: float, dof: int = NEES_DOF, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the mean of ``n`` independent chi-square(``dof``) values.

    ``n * mean ~ chi2(n * dof)``, so the band is ``chi2_{n dof}.ppf((1 -+ c) / 2) / n``; ``n``
    may be an effective (non-integer) count. (NaN, NaN) for ``n < 1``.
    """
    from scipy.stats import chi2

    if n < 1:
        return math.nan, math.nan
    a = (1.0 - confidence) / 2.0
    return float(chi2.ppf(a, n * dof) / n), float(chi2.ppf(1.0 - a, n * dof) / n)


def autocorrelation_time(x: FloatArray, window: float = 5.0) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_k rho_k`` of a series (Sokal's automatic
    window: the sum stops at the first lag ``M >= window * tau(M)``); 1 for white noise, clipped
    to ``[1, len(x)]``. Non-finite values are dropped first."""
    v = np.asarray(x, dtype=np.float64)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 4:
        return 1.0
    v = v - v.mean()
    f = np.fft.rfft(v, n=2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    if not acf[0] > 0.0:
        return 1.0
    tau = 2.0 * np.cumsum(acf / acf[0]) - 1.0
    m = np.arange(n)
    stop = np.flatnonzero(m >= window * tau)
    t = float(tau[stop[0]] if stop.size else tau[-1])
    return min(max(t, 1.0), float(n))


def effective_count(series: Iterable[FloatArray]) -> float:
    """Independent samples in time-correlated runs: each run's finite count over its
    :func:`autocorrelation_time`, summed."""
    total = 0.0
    for x in series:
        v = np.asarray(x, dtype=np.float64)
        k = int(np.isfinite(v).sum())
        if k:
            total += k / autocorrelation_time(v)
    return total


def _finite_mean(x: FloatArray) -> tuple[float, int]:
    f = x[np.isfinite(x)]
    return (float(f.mean()) if f.size else math.nan), int(f.size)


def summarise(label: str, records: Sequence[RunRecord], wall_s: float | None = None) -> dict[str, Any]:
    """One table row over a target's runs (or over all runs for the total row)."""
    n = len(records)
    docked = sum(r.docked for r in records)
    lo, hi = wilson_interval(docked, n)
    cat = (lambda k: np.concatenate([getattr(r, k) for r in records]) if records else np.zeros(0))
    err, pl, deg = cat("port_err_m"), cat("pl_m"), cat("degraded").astype(bool)
    mis = err > pl + ERROR_SLACK_M
    hmi = mis & ~deg
    frames = int(err.size)
    ok = ~deg
    np_mean, _ = _finite_mean(cat("nees_pos"))
    na_mean, _ = _finite_mean(cat("nees_att"))
    np_eff = effective_count(r.nees_pos for r in records)
    na_eff = effective_count(r.nees_att for r in records)
    band_p, band_a = nees_band(np_eff), nees_band(na_eff)
    ok_np, _ = _finite_mean(cat("nees_pos")[ok]) if frames else (math.nan, 0)
    terms = Counter(r.outcome for r in records)
    return {
        "target": label,
        "runs": n,
        "docked_pct": 100.0 * docked / n if n else math.nan,
        "wilson95_lo_pct": 100.0 * lo,
        "wilson95_hi_pct": 100.0 * hi,
        "terminations": ", ".join(f"{k} {v}" for k, v in sorted(terms.items())),
        "frames": frames,
        "degraded_frac": float(deg.mean()) if frames else math.nan,
        "hmi": int(hmi.sum()),
        "hmi_rate": float(hmi.mean()) if frames else math.nan,
        "hmi_over_0.1m": int((hmi & (err > 0.1)).sum()),
        "mi": int(mis.sum()),
        "mi_rate": float(mis.mean()) if frames else math.nan,
        "max_err_valid_m": float(err[ok].max()) if ok.any() else math.nan,
        "max_err_m": float(err.max()) if frames else math.nan,
        "nees_pos": np_mean,
        "nees_pos_valid": ok_np,
        "nees_att": na_mean,
        "nees_los": _finite_mean(cat("nees_los"))[0],
        "nees_across": _finite_mean(cat("nees_across"))[0],
        "nees_pos_band_lo": band_p[0], "nees_pos_band_hi": band_p[1],
        "nees_att_band_lo": band_a[0], "nees_att_band_hi": band_a[1],
        "nees_pos_n_eff": np_eff, "nees_att_n_eff": na_eff,
        "wall_s": float(sum(r.wall_s for r in records)) if wall_s is None else float(wall_s),
    }


def by_range(records: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """Frames, degraded fraction, HMI, MI, the largest valid port error, the median PL and the
    mean NEES (position, attitude; position along the line of sight and across it) per range bin
    (:data:`RANGE_BINS_M`, true sensor-to-port range) over all the records' pose frames."""
    if not records:
        return []
    cat = (lambda k: np.concatenate([getattr(r, k) for r in records]))
    rng, err, pl = cat("range_m"), cat("port_err_m"), cat("pl_m")
    deg = cat("degraded").astype(bool)
    n_p, n_a, n_l, n_x = cat("nees_pos"), cat("nees_att"), cat("nees_los"), cat("nees_across")
    mis = err > pl + ERROR_SLACK_M
    out = []
    for lo, hi in RANGE_BINS_M:
        m = (rng >= lo) & (rng < hi)
        n = int(m.sum())
        if n == 0:
            continue
        ok = m & ~deg
        out.append({
            "range [m]": f"{lo:g}-{hi:g}" if math.isfinite(hi) else f"> {lo:g}",
            "frames": n,
            "degraded": float(deg[m].mean()),
            "HMI": int((mis & ok).sum()),
            "MI": int((mis & m).sum()),
            "max err valid [m]": float(err[ok].max()) if ok.any() else math.nan,
            "median PL [m]": float(np.median(pl[m])),
            "NEES pos": _finite_mean(n_p[m])[0],
            "NEES att": _finite_mean(n_a[m])[0],
            "NEES pos along LOS (1)": _finite_mean(n_l[m])[0],
            "NEES pos across (2)": _finite_mean(n_x[m])[0],
        })
    return out


def _fmt(v: float, spec: str = ".3g") -> str:
    return "nan" if not np.isfinite(v) else format(v, spec)


def display_row(row: dict[str, Any]) -> dict[str, Any]:
    """The printed columns of a :func:`summarise` row."""
    frames = row["frames"]
    return {
        "target": row["target"],
        "runs": row["runs"],
        "docked [95% CI]": f"{row['docked_pct']:.0f}% [{row['wilson95_lo_pct']:.0f}-{row['wilson95_hi_pct']:.0f}]",
        "terminations": row["terminations"],
        "pose frames": frames,
        "degraded": _fmt(row["degraded_frac"], ".2f"),
        "HMI": f"{row['hmi']}/{frames} ({_fmt(row['hmi_rate'], '.1e')})",
        "MI": f"{row['mi']}/{frames} ({_fmt(row['mi_rate'], '.1e')})",
        "max err valid [m]": _fmt(row["max_err_valid_m"]),
        "NEES pos [band]": f"{_fmt(row['nees_pos'])} [{_fmt(row['nees_pos_band_lo'], '.2f')}-{_fmt(row['nees_pos_band_hi'], '.2f')}]",
        "NEES att [band]": f"{_fmt(row['nees_att'])} [{_fmt(row['nees_att_band_lo'], '.2f')}-{_fmt(row['nees_att_band_hi'], '.2f')}]",
        "wall [s]": _fmt(row["wall_s"], ".0f"),
    }


# --------------------------------------------------------------------------- output
def new_folder(path: Path, kind: str = "bench-integrity") -> Path:
    """Create ``path`` as a new folder marked for ``kind`` (:mod:`agents.outputs`); an existing one
    gets a ``-2``, ``-3``... sibling instead (results are never written over)."""
    from agents.outputs import OutputFolderError, claim_folder

    k, p = 1, path
    while True:
        try:
            return claim_folder(p, kind, new=True)
        except OutputFolderError:
            k += 1
            p = path.with_name(f"{path.name}-{k}")


def write_rows(folder: Path, rows: Sequence[dict[str, Any]], meta: dict[str, Any]) -> list[Path]:
    """``rows.csv`` and ``rows.json`` (with ``meta``) in ``folder`` (created fresh by the caller)."""
    import csv

    keys = list(rows[0].keys()) if rows else []
    csv_path = folder / "rows.csv"
    with csv_path.open("x", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    json_path = folder / "rows.json"
    with json_path.open("x") as f:
        json.dump({"meta": meta, "rows": list(rows)}, f, indent=2, default=str)
    return [csv_path, json_path]


def plot_error_vs_pl(path: Path, groups: Iterable[tuple[str, Sequence[RunRecord]]], max_points: int = 4000) -> Path:
    """Scatter of port error against protection level per target (log-log) with ``y = x``:
    points above the line are misleading, filled markers valid (HMI when above), hollow degraded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6.5), dpi=110)
    lo, hi = math.inf, 0.0
    colors = plt.get_cmap("tab10")
    for i, (label, recs) in enumerate(groups):
        if not recs:
            continue
        err = np.concatenate([r.port_err_m for r in recs])
        pl = np.concatenate([r.pl_m for r in recs])
        deg = np.concatenate([r.degraded for r in recs]).astype(bool)
        m = (err > 0) & (pl > 0)
        err, pl, deg = err[m], pl[m], deg[m]
        if err.size == 0:
            continue
        stride = max(1, int(math.ceil(err.size / max_points)))  # deterministic thinning
        err, pl, deg = err[::stride], pl[::stride], deg[::stride]
        c = colors(i % 10)
        ax.scatter(pl[~deg], err[~deg], s=5, color=c, alpha=0.5, label=f"{label} ({m.sum()} frames)")
        if deg.any():
            ax.scatter(pl[deg], err[deg], s=9, facecolors="none", edgecolors=c, alpha=0.5, linewidths=0.6)
        lo, hi = min(lo, pl.min(), err.min()), max(hi, pl.max(), err.max())
    if hi > 0 and np.isfinite(lo):
        xs = np.array([lo, hi])
        ax.plot(xs, xs, "k--", lw=1, label="error = PL")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("protection level [m]")
    ax.set_ylabel("port position error [m]")
    ax.set_title("port error vs protection level (hollow: degraded; above the line: misleading)")
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(True, which="both", alpha=0.2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=int, default=4, help="runs per target (default 4)")
    p.add_argument("--seeds-offset", type=int, default=0,
                   help="run i uses reset seed offset + i (default 0)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="cap on env steps per run (default: the mission's max_episode_steps)")
    p.add_argument("--all", action="store_true", help="add the library's hubble")
    p.add_argument("--targets", nargs="*", default=None, metavar="LABEL",
                   help="only these targets (library names or generated kinds, e.g. cubesat flat_face)")
    p.add_argument("--shape-seed", type=int, default=SHAPE_SEED,
                   help=f"seed of every generated shape (default {SHAPE_SEED}, never tuned on)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="mission override on every target, nested with '.' or '__' "
                        "(pipeline.integrity.accuracy_calibration=true); repeatable; VALUE is parsed as YAML")
    p.add_argument("--out", type=Path, default=None,
                   help="report folder (default reports/bench-integrity-<UTC time>/; a new folder)")


def _cases(args: argparse.Namespace, folder: Path) -> list[TargetCase]:
    from perception.shapes import SHAPE_KINDS

    names = list(LIBRARY_TARGETS) + (["hubble"] if args.all else [])
    want = set(args.targets) if args.targets else None
    cases = [library_case(n) for n in names if want is None or n in want]
    for kind in SHAPE_KINDS:
        if want is None or kind in want:
            cases.append(generated_case(kind, args.shape_seed, folder))
    if want is not None:
        known = set(names) | set(SHAPE_KINDS) | {"hubble"}
        unknown = sorted(want - known)
        if unknown:
            raise ValueError(f"--targets {' '.join(unknown)}: unknown; expected among {sorted(known)}")
        if "hubble" in want and not args.all:
            cases.insert(0, library_case("hubble"))
    return cases


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from agents.benchmarks.timing import format_table

    if args.runs < 1:
        raise ValueError(f"--runs={args.runs}; expected >= 1")
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    out = new_folder(args.out if args.out is not None else Path("reports") / f"bench-integrity-{stamp}")
    seeds = [args.seeds_offset + i for i in range(args.runs)]
    from agents.commands.demo import parse_overrides

    extra = parse_overrides(getattr(args, "overrides", []) or [])
    rows: list[dict[str, Any]] = []
    groups: list[tuple[str, list[RunRecord]]] = []
    per_run: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-integrity-") as tmp:
        cases = _cases(args, Path(tmp))
        bar = tqdm(total=len(cases) * len(seeds), desc="integrity", unit="run", mininterval=1.0)
        for case in cases:
            t0 = time.perf_counter()
            env = make_case_env(case, "tridar", **extra)
            recs: list[RunRecord] = []
            try:
                for s in seeds:
                    bar.set_postfix_str(f"{case.label} seed {s}")
                    rec = fly(env, s, max_steps=args.max_steps)
                    rec.label = case.label
                    recs.append(rec)
                    per_run.append(rec.summary())
                    bar.update()
            finally:
                env.close()
            rows.append(summarise(case.label, recs, time.perf_counter() - t0))
            groups.append((case.label, recs))
        bar.close()
    all_recs = [r for _, recs in groups for r in recs]
    rows.append(summarise("total", all_recs, sum(r["wall_s"] for r in rows)))
    print(f"integrity: {'stock ' if not extra else ''}final_approach"
          f"{' with ' + ', '.join(f'{k}={v}' for k, v in extra.items()) if extra else ''}, "
          f"glideslope, perception=tridar, {args.runs} runs/target "
          f"(reset seeds {seeds[0]}..{seeds[-1]}), generated shapes seed {args.shape_seed}, "
          f"max steps {args.max_steps or 'mission'}")
    print(format_table([display_row(r) for r in rows]))
    print("HMI: valid (not degraded) pose with port error > PL; MI: any published pose with error > PL. "
          "NEES bands: 95 % of a mean of chi2(3) values over the effective number of independent "
          "frames (each run's frames over the integrated autocorrelation time of its NEES).")
    meta = {"runs": args.runs, "seeds": seeds, "shape_seed": args.shape_seed,
            "max_steps": args.max_steps, "mission": "final_approach", "controller": "glideslope",
            "perception": "tridar", "targets": [c.label for c in cases],
            "overrides": {c.label: {**c.overrides, **extra} for c in cases}}
    ranges = by_range(all_recs)
    print("all targets by range to the port:")
    print(format_table(ranges))
    files = write_rows(out, rows, meta)
    import csv

    by_range_path = out / "by_range.csv"
    with by_range_path.open("x", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(ranges[0].keys()) if ranges else ["range [m]"])
        w.writeheader()
        w.writerows(ranges)
    frames_path = out / "frames.npz"  # per-frame arrays of every run, for later analysis
    arrays: dict[str, Any] = {}
    for i, rec in enumerate(all_recs):
        for k in ("range_m", "port_err_m", "att_err_rad", "pl_m", "al_m", "degraded", "nees_pos", "nees_att",
                  "nees_los", "nees_across"):
            arrays[f"{i:03d}_{k}"] = getattr(rec, k)
    np.savez_compressed(frames_path, labels=np.array([f"{r.label} seed {r.seed} {r.outcome}" for r in all_recs]),
                        **arrays)
    files += [by_range_path, frames_path]
    runs_path = out / "runs.json"
    with runs_path.open("x") as f:
        json.dump(per_run, f, indent=2)
    png = plot_error_vs_pl(out / "error_vs_pl.png", groups)
    print("wrote " + ", ".join(str(p) for p in [*files, runs_path, png]))
    return 0
