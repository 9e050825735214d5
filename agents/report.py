"""Fly one recorded episode and write its report folder (the ``demo`` / ``run`` commands).

:func:`fly` wraps the env in :class:`EpisodeRecorder` (per-step truth, estimate, mode and action,
plus a rendered frame every ``render_every`` steps), flies it with :func:`agents.episode.run_episode`
and returns an :class:`EpisodeRecord`. :func:`write_report` turns that into a folder::

    config.yaml        the resolved mission config
    summary.json       outcome, totals, contact vs envelope, mode timeline, estimation errors
    summary.txt        the one-screen summary (:func:`format_summary`)
    log.csv            per-step log (:data:`LOG_FIELDS`); log.parquet too when pyarrow is present
    trajectory.png     Hill-frame path (truth and TriDAR estimate), docking-frame approach
    errors_vs_range.png  estimation errors vs true range
    modes.png          TriDAR mode timeline with range and points per frame
    modes_range.png    the phases (thermal bearing, LIDAR bearing, search, tracking, contact) over
                       the true range on a log axis, with the range measurement's error
    contact.png        closing conditions against the capture envelope
    episode.mp4        rendered frames (imageio-ffmpeg), else episode.gif (Pillow)

plus the marker of :mod:`agents.outputs` (a report is written only into a new or empty folder, or
over an earlier report).

The controller never sees what the recorder logs: the recorder reads ``info`` truth and the env's
public state after each step, for the record only.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import numpy.typing as npt

from agents.episode import EpisodeResult, Policy, run_episode
from agents.outputs import json_safe
from perception.config import MissionConfig, save_config
from perception.geometry import invert
from tridar_env.env import observation_slices

_S = observation_slices()
#: Marker kind of a report folder (:mod:`agents.outputs`).
KIND = "report"

#: Columns of the report's per-step log (SI units; ``*_true`` is simulator truth, ``*_est`` the
#: TriDAR estimate the controller saw, ``nan`` where the estimate was not valid).
LOG_FIELDS: tuple[str, ...] = (
    "step", "t", "mode", "phase", "pose_valid",
    "x_lvlh", "y_lvlh", "z_lvlh", "vx_lvlh", "vy_lvlh", "vz_lvlh",
    "x_lvlh_est", "y_lvlh_est", "z_lvlh_est",
    "port_x_true", "port_y_true", "port_z_true",
    "port_x_est", "port_y_est", "port_z_est",
    "port_vx_est", "port_vy_est", "port_vz_est",
    "range_true", "range_est", "range_rate_est",
    "pos_err_m", "att_err_deg", "n_points", "fitness",
    "axial_distance", "lateral_offset", "closing_speed", "lateral_speed",
    "misalignment_deg", "angular_rate_deg_s",
    "a0", "a1", "a2", "a3", "a4", "a5",
    "reward", "propellant_kg", "delta_v",
)

MODES = ("bearing", "search", "tracking")
_MODE_COLORS = {"bearing": "tab:orange", "search": "tab:red", "tracking": "tab:green"}
#: The phases of a profile (seed 000 section 5): bearing split by what measured the bearing.
_PHASE_COLORS = {"thermal bearing": "tab:purple", "LIDAR bearing": "tab:orange", "bearing": "tab:brown",
                 "search": "tab:red", "tracking": "tab:green", "contact": "k"}


def phase_of(mode: str, bearing_source: str) -> str:
    """The profile phase of a step: ``thermal bearing`` / ``LIDAR bearing`` in bearing mode (by
    what measured the bearing; ``bearing`` with none), else the mode."""
    if mode != "bearing":
        return mode
    return {"thermal": "thermal bearing", "lidar": "LIDAR bearing"}.get(bearing_source, "bearing")


class EpisodeRecorder(gym.Wrapper):
    """Records every step of an episode and renders a frame every ``render_every`` steps.

    Args:
        env: a ``DockingEnv`` (possibly wrapped); ``render_every > 0`` needs
            ``render_mode="rgb_array"``.
        render_every: render after every N-th step (and the first and last); 0 for none.

    Attributes:
        rows: one dict per step with the keys of :data:`LOG_FIELDS`.
        frames: rendered ``(H, W, 3) uint8`` frames.
        frame_steps: the step index of each frame.
    """

    def __init__(self, env: gym.Env, render_every: int = 0) -> None:
        super().__init__(env)
        if render_every < 0:
            raise ValueError(f"render_every={render_every}; expected >= 0")
        if render_every and env.render_mode != "rgb_array":
            raise ValueError(f"render_every={render_every} needs render_mode='rgb_array', "
                             f"got {env.render_mode!r}")
        self.render_every = render_every
        self.rows: list[dict[str, Any]] = []
        self.frames: list[npt.NDArray[np.uint8]] = []
        self.frame_steps: list[int] = []
        self._n = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.rows, self.frames, self.frame_steps, self._n = [], [], [], 0
        if self.render_every:
            self._frame()
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._n += 1
        self.rows.append(self._row(obs, float(reward), info, np.asarray(action, dtype=np.float64)))
        if self.render_every and (self._n % self.render_every == 0 or terminated or truncated):
            self._frame()
        return obs, reward, terminated, truncated, info

    def _frame(self) -> None:
        frame = self.env.render()
        if frame is not None:
            self.frames.append(np.asarray(frame, dtype=np.uint8))
            self.frame_steps.append(self._n)

    def _row(self, obs: npt.NDArray[np.floating], reward: float, info: dict[str, Any],
             action: npt.NDArray[np.float64]) -> dict[str, Any]:
        base = self.env.unwrapped
        w = base.world
        valid = obs[_S["valid"]]
        pose = bool(valid[3] > 0.5 and valid[5] > 0.5)
        nan3 = np.full(3, np.nan)
        port_true = (invert(w.T_lvlh_dock) @ w.T_lvlh_port)[:3, 3]
        est_r = base.history[-1].get("est_r") if base.history else None
        c = info["contact"]
        acts = np.full(6, np.nan)
        acts[: action.size] = action
        sv = base.state_vector
        phase = phase_of(info["mode"], sv.bearing_source if sv is not None else "")
        if info.get("termination") in ("docked", "collision"):
            phase = "contact"
        row: dict[str, Any] = {
            "step": self._n, "t": float(info["t"]), "mode": info["mode"], "phase": phase,
            "pose_valid": pose,
        }
        row.update(zip(("x_lvlh", "y_lvlh", "z_lvlh"), map(float, info["truth_r_lvlh"])))
        row.update(zip(("vx_lvlh", "vy_lvlh", "vz_lvlh"), map(float, info["truth_v_lvlh"])))
        row.update(zip(("x_lvlh_est", "y_lvlh_est", "z_lvlh_est"),
                       map(float, est_r if est_r is not None else nan3)))
        row.update(zip(("port_x_true", "port_y_true", "port_z_true"), map(float, port_true)))
        row.update(zip(("port_x_est", "port_y_est", "port_z_est"),
                       map(float, obs[_S["port_position_dock"]] if pose else nan3)))
        row.update(zip(("port_vx_est", "port_vy_est", "port_vz_est"),
                       map(float, obs[_S["port_velocity_dock"]] if valid[4] > 0.5 else nan3)))
        row.update(
            range_true=float(np.linalg.norm(info["truth_T_sensor_target"][:3, 3])),
            range_est=float(obs[_S["range"]][0]) if valid[1] > 0.5 else np.nan,
            range_rate_est=float(obs[_S["range_rate"]][0]) if valid[2] > 0.5 else np.nan,
            pos_err_m=float(info.get("estimate_position_error_m", float("nan"))),
            att_err_deg=float(info.get("estimate_attitude_error_deg", float("nan"))),
            n_points=int(info["n_points"]), fitness=float(obs[_S["fitness"]][0]),
            **{k: float(v) for k, v in asdict(c).items()},
            **{f"a{i}": float(acts[i]) for i in range(6)},
            reward=reward, propellant_kg=float(info["propellant_kg"]), delta_v=float(info["delta_v"]),
        )
        return row


@dataclass
class EpisodeRecord:
    """One recorded episode: the summary, the per-step log and the frames.

    Attributes:
        result: :class:`~agents.episode.EpisodeResult` of the episode.
        cfg: the resolved mission config the env ran.
        env_name: Gymnasium id or mission file it came from.
        controller: controller name.
        perception: perception mode.
        rows: per-step log (:data:`LOG_FIELDS`).
        frames: rendered frames and their step indices.
        wall_time_s: wall-clock time of the flight [s] (rendering included).
    """

    result: EpisodeResult
    cfg: MissionConfig
    env_name: str
    controller: str
    perception: str
    rows: list[dict[str, Any]]
    frames: list[npt.NDArray[np.uint8]] = field(default_factory=list, repr=False)
    frame_steps: list[int] = field(default_factory=list)
    wall_time_s: float = 0.0

    def column(self, name: str) -> npt.NDArray[Any]:
        """One log column as an array."""
        return np.asarray([r[name] for r in self.rows])


def fly(
    env: gym.Env,
    policy: Policy,
    seed: int,
    *,
    env_name: str,
    controller: str,
    render_every: int = 0,
    max_steps: int | None = None,
    on_step: Callable[[int], None] | None = None,
) -> EpisodeRecord:
    """Fly one recorded episode.

    Args:
        env: the env (``render_mode="rgb_array"`` when ``render_every > 0``).
        policy: ``obs -> action`` (a controller with ``reset()`` is reset first).
        seed: reset seed.
        env_name: label for the report (id or mission file).
        controller: label for the report.
        render_every: keep a frame every N steps (0: no frames).
        max_steps: optional cap on the number of steps.
        on_step: progress callback with the step index.
    """
    rec = EpisodeRecorder(env, render_every)
    t0 = time.perf_counter()
    result = run_episode(rec, policy, seed, max_steps=max_steps, on_step=on_step)
    wall = time.perf_counter() - t0
    cfg = env.unwrapped.cfg
    return EpisodeRecord(
        result=result, cfg=cfg, env_name=env_name, controller=controller,
        perception=cfg.env.perception, rows=rec.rows, frames=rec.frames,
        frame_steps=rec.frame_steps, wall_time_s=wall,
    )


# ---------------------------------------------------------------------- summary
def mode_timeline(t: Sequence[float], modes: Sequence[str], dt: float) -> list[tuple[str, float, float]]:
    """Collapse per-step modes into ``(mode, t_start, t_end)`` segments [s]."""
    out: list[tuple[str, float, float]] = []
    prev = None
    for ti, m in zip(t, modes):
        # A step starts where the last one ended (steps may lengthen with range).
        start = float(ti) - dt if prev is None else prev
        prev = float(ti)
        if out and out[-1][0] == m:
            out[-1] = (m, out[-1][1], float(ti))
        else:
            out.append((m, max(start, 0.0), float(ti)))
    return out


def envelope_check(cfg: MissionConfig, contact: dict[str, float]) -> list[dict[str, Any]]:
    """Final contact conditions against the capture envelope, one dict per condition."""
    e = cfg.env.envelope
    rows = [
        ("closing speed", "m/s", contact["closing_speed"], e.axial_speed_min_m_s, e.axial_speed_max_m_s),
        ("lateral offset", "m", contact["lateral_offset"], None, e.lateral_offset_max_m),
        ("lateral speed", "m/s", contact["lateral_speed"], None, e.lateral_speed_max_m_s),
        ("misalignment", "deg", contact["misalignment_deg"], None, e.misalignment_max_deg),
        ("angular rate", "deg/s", contact["angular_rate_deg_s"], None, e.angular_rate_max_deg_s),
    ]
    out = []
    for name, unit, value, lo, hi in rows:
        ok = value <= hi and (lo is None or value >= lo)
        out.append({"name": name, "unit": unit, "value": float(value), "min": lo, "max": hi, "ok": bool(ok)})
    return out


def summary_dict(record: EpisodeRecord) -> dict[str, Any]:
    """Everything the summary shows, as JSON-ready values."""
    r = record.result
    cfg = record.cfg
    dt = cfg.env.frame_period_s * cfg.env.frame_skip
    timeline = mode_timeline(record.column("t").tolist(), record.column("mode").tolist(), dt)
    return {
        "env": record.env_name, "controller": record.controller, "perception": record.perception,
        "seed": r.seed, "outcome": r.outcome, "docked": r.docked, "steps": r.steps,
        "sim_time_s": r.sim_time_s, "wall_time_s": record.wall_time_s,
        "delta_v_m_s": r.delta_v_m_s, "propellant_used_kg": r.propellant_used_kg,
        "episode_return": r.episode_return, "contact": r.contact,
        "envelope": envelope_check(cfg, r.contact),
        "mode_timeline": [{"mode": m, "start_s": a, "end_s": b} for m, a, b in timeline],
        "phase_timeline": phase_segments(record),
        "time_in_mode_s": r.time_in_mode_s, "acquisitions": r.acquisitions,
        "max_pos_err_m": r.max_pos_err_m, "rms_pos_err_m": r.rms_pos_err_m,
        "max_att_err_deg": r.max_att_err_deg, "rms_att_err_deg": r.rms_att_err_deg,
        "frames": len(record.frames),
    }


def _fmt_limit(c: dict[str, Any]) -> str:
    return f"{c['min']:g} .. {c['max']:g}" if c["min"] is not None else f"<= {c['max']:g}"


def format_summary(s: dict[str, Any], out_dir: Path | None = None) -> str:
    """The one-screen text summary of :func:`summary_dict`."""
    lines = [
        f"{s['env']}  controller={s['controller']}  perception={s['perception']}  seed={s['seed']}",
        (f"result       {s['outcome'].upper()} after {s['sim_time_s']:.1f} s simulated "
         f"({s['steps']} steps, {s['wall_time_s']:.1f} s wall)"),
        f"delta-v      {s['delta_v_m_s']:.3f} m/s  (propellant {s['propellant_used_kg']:.3f} kg)",
        "contact      " + ("at capture" if s["outcome"] in ("docked", "collision")
                           else "at the end of the episode (no contact)"),
    ]
    for c in s["envelope"]:
        lines.append(f"  {c['name']:<15} {c['value']:9.4f} {c['unit']:<6} envelope "
                     f"{_fmt_limit(c):<13} {'ok' if c['ok'] else 'OUT'}")
    segs = [f"{d['mode']} {d['start_s']:.1f}-{d['end_s']:.1f}" for d in s["mode_timeline"]]
    if len(segs) > 4:  # keep it on one line: the first segment and the last two
        segs = segs[:1] + [f"...{len(segs) - 3} more..."] + segs[-2:]
    lines.append(f"modes [s]    {', '.join(segs)}; {s['acquisitions']} acquisition(s)")
    firsts: dict[str, float] = {}  # each phase's first range, in order
    for d in s.get("phase_timeline", []):
        firsts.setdefault(d["phase"], d["range_start_m"])
    if firsts:
        lines.append("phases       " + " -> ".join(f"{p} from {r:.0f} m" for p, r in firsts.items()))
    if np.isfinite(s["max_pos_err_m"]):
        lines.append(
            f"estimation   max error {100 * s['max_pos_err_m']:.2f} cm / {s['max_att_err_deg']:.2f} deg "
            f"(rms {100 * s['rms_pos_err_m']:.2f} cm / {s['rms_att_err_deg']:.2f} deg)"
        )
    else:
        lines.append("estimation   no valid pose during the episode")
    if out_dir is not None:
        lines.append(f"report       {out_dir}")
    return "\n".join(lines)


# ---------------------------------------------------------------------- files
def write_log(rows: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    """``log.csv`` always, ``log.parquet`` when pyarrow is importable."""
    paths = [out_dir / "log.csv"]
    with paths[0].open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(LOG_FIELDS))
        w.writeheader()
        w.writerows(rows)
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return paths
    table = pa.table({k: [r[k] for r in rows] for k in LOG_FIELDS})
    pq.write_table(table, out_dir / "log.parquet")
    paths.append(out_dir / "log.parquet")
    return paths


def write_video(frames: Sequence[npt.NDArray[np.uint8]], out_dir: Path, fps: int = 10) -> Path | None:
    """``episode.mp4`` through imageio-ffmpeg when available, else ``episode.gif`` (Pillow)."""
    if not frames:
        return None
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the binary behind imageio's ffmpeg plugin)

        path = out_dir / "episode.mp4"
        with imageio.get_writer(path, fps=fps, codec="libx264", quality=7,
                                macro_block_size=16, ffmpeg_log_level="error") as w:
            for f in frames:
                w.append_data(f)
        return path
    except ImportError:
        pass
    from PIL import Image

    path = out_dir / "episode.gif"
    imgs = [Image.fromarray(f) for f in frames]
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(1000 / fps), loop=0)
    return path


def _figure(w: float, h: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=100, layout="constrained")


def plot_trajectory(rec: EpisodeRecord, path: Path) -> Path:
    """Hill-frame path (V-bar horizontal, R-bar up) and the approach along the port axis."""
    fig = _figure(11, 4.5)
    ax1, ax2 = fig.subplots(1, 2)
    names = ("x", "y", "z")
    labels = {"x": "R-bar x [m]", "y": "V-bar y [m]", "z": "orbit normal z [m]"}
    true = np.column_stack([rec.column(f"{a}_lvlh") for a in names]).astype(float)
    est = np.column_stack([rec.column(f"{a}_lvlh_est") for a in names]).astype(float)
    # V-bar horizontal and R-bar up, unless the path runs mostly out of that plane
    span = np.ptp(true, axis=0)
    h, v = (1, 0) if span[2] <= max(span[0], span[1]) else ((1, 2) if span[1] >= span[0] else (0, 2))
    ax1.plot(true[:, h], true[:, v], "k-", lw=1.2, label="truth")
    ax1.plot(est[:, h], est[:, v], ".", color="tab:red", ms=1.5, label="TriDAR estimate")
    ax1.plot(true[:1, h], true[:1, v], "o", color="tab:blue", label="start")
    ax1.plot(true[-1:, h], true[-1:, v], "s", color="tab:blue", label="end")
    ax1.plot([0], [0], "+", color="0.4", ms=10, label="target CoM")
    ax1.set(xlabel=labels[names[h]], ylabel=labels[names[v]], title="Chaser in the target's Hill frame")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.legend(fontsize=8)
    # like with like: the port in the docking frame, as simulated and as the controller saw it
    pt = np.column_stack([rec.column(f"port_{a}_true") for a in "xyz"]).astype(float)
    pe = np.column_stack([rec.column(f"port_{a}_est") for a in "xyz"]).astype(float)
    z, lat = pt[:, 2], np.hypot(pt[:, 0], pt[:, 1])
    ax2.plot(pe[:, 2], np.hypot(pe[:, 0], pe[:, 1]), "-", color="tab:red", lw=0.8, alpha=0.6,
             label="TriDAR estimate")
    ax2.plot(z, lat, "k-", lw=1.2, label="truth")
    lim = rec.cfg.env.envelope.lateral_offset_max_m
    top = 1.3 * max(float(np.nanmax(lat)), lim)
    half = rec.cfg.env.corridor_half_angle_deg
    zmax = float(np.nanmax(z))
    if half is not None:
        zz = np.linspace(0.0, zmax, 200)
        ax2.plot(zz, zz * np.tan(np.radians(half)), "--", color="tab:green", lw=0.8, label="corridor")
    ax2.axhline(lim, color="tab:orange", lw=0.8, label="capture lateral limit")
    ax2.set(xlabel="port ahead along the docking axis [m]", ylabel="port off the docking axis [m]",
            title="The port seen from the docking frame")
    ax2.set_xscale("symlog", linthresh=1.0)
    ax2.set_xlim(min(float(np.nanmin(z)), 0.0), zmax * 1.1)
    ax2.set_ylim(0.0, top)
    ax2.invert_xaxis()
    ax2.legend(fontsize=8)
    fig.savefig(path)
    return path


def plot_errors(rec: EpisodeRecord, path: Path) -> Path:
    """Estimation errors (position [cm], attitude [deg]) against the true range."""
    fig = _figure(8, 5)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    rng = rec.column("range_true").astype(float)
    pe = rec.column("pos_err_m").astype(float)
    ae = rec.column("att_err_deg").astype(float)
    ok = np.isfinite(pe)
    ax1.plot(rng[ok], 100 * pe[ok], ".", ms=2, color="tab:blue")
    ax1.set(ylabel="position error [cm]", title="TriDAR estimate error vs range (valid pose)")
    ax2.plot(rng[ok], ae[ok], ".", ms=2, color="tab:purple")
    ax2.set(xlabel="true range [m]", ylabel="attitude error [deg]")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.set_xscale("log")
        ax.invert_xaxis()
    if not ok.any():
        ax1.text(0.5, 0.5, "no valid pose", transform=ax1.transAxes, ha="center")
    fig.savefig(path)
    return path


def plot_modes(rec: EpisodeRecord, path: Path) -> Path:
    """Mode timeline bar above the range and the points per frame."""
    from matplotlib.patches import Patch

    fig = _figure(9, 5)
    ax0, ax1 = fig.subplots(2, 1, sharex=True, height_ratios=[1, 3])
    dt = rec.cfg.env.frame_period_s * rec.cfg.env.frame_skip
    for m, a, b in mode_timeline(rec.column("t").tolist(), rec.column("mode").tolist(), dt):
        ax0.barh(0, b - a, left=a, color=_MODE_COLORS.get(m, "0.5"), edgecolor="none")
    handles = [Patch(color=c, label=m) for m, c in _MODE_COLORS.items()]
    ax0.legend(handles=handles, ncol=3, fontsize=8, loc="upper right")
    ax0.set(yticks=[], title="TriDAR mode timeline")
    t = rec.column("t").astype(float)
    ax1.plot(t, rec.column("range_true"), "k-", lw=1, label="true range")
    ax1.plot(t, rec.column("range_est").astype(float), ".", color="tab:red", ms=1.5, label="measured range")
    ax1.set(xlabel="time [s]", ylabel="range [m]")
    ax1.legend(loc="upper right", fontsize=8)
    axr = ax1.twinx()
    axr.plot(t, rec.column("n_points"), "-", color="tab:gray", lw=0.6, alpha=0.6)
    axr.set_ylabel("points per frame", color="tab:gray")
    fig.savefig(path)
    return path


def phase_segments(rec: EpisodeRecord) -> list[dict[str, Any]]:
    """The profile's phases in order, each with its time span [s] and true range span [m]."""
    t = rec.column("t").astype(float)
    rng = rec.column("range_true").astype(float)
    phases = rec.column("phase").tolist()
    out: list[dict[str, Any]] = []
    for i, ph in enumerate(phases):
        if out and out[-1]["phase"] == ph:
            out[-1].update(end_s=float(t[i]), range_end_m=float(rng[i]))
        else:
            out.append({"phase": ph, "start_s": float(t[i - 1]) if i else 0.0, "end_s": float(t[i]),
                        "range_start_m": float(rng[i]), "range_end_m": float(rng[i])})
    return out


def plot_mode_ranges(rec: EpisodeRecord, path: Path) -> Path:
    """The phases over the true range (log axis, closing to the right), and the range
    measurement's error against the same axis."""
    from matplotlib.patches import Patch

    fig = _figure(9, 5)
    ax0, ax1 = fig.subplots(2, 1, sharex=True, height_ratios=[1, 3])
    rng = np.maximum(rec.column("range_true").astype(float), 0.1)
    phases = rec.column("phase").tolist()
    for i in range(len(rng)):
        a = rng[i - 1] if i else rng[i] * 1.02
        ax0.fill_betweenx([0, 1], a, rng[i], color=_PHASE_COLORS.get(phases[i], "0.5"), lw=0)
    seen = [p for p in _PHASE_COLORS if p in set(phases)]
    ax0.legend(handles=[Patch(color=_PHASE_COLORS[p], label=p) for p in seen], ncol=len(seen) or 1,
               fontsize=7, loc="upper left")
    ax0.set(yticks=[], title="TriDAR phases over range")
    err = np.abs(rec.column("range_est").astype(float) - rng)
    ok = np.isfinite(err)
    for ph in seen:
        m = ok & (np.asarray(phases) == ph)
        if m.any():
            ax1.plot(rng[m], np.maximum(err[m], 1e-3), ".", ms=2, color=_PHASE_COLORS[ph], label=ph)
    ax1.set(xlabel="true range [m] (log)", ylabel="|measured - true range| [m]")
    ax1.set_yscale("log")
    for ax in (ax0, ax1):
        ax.set_xscale("log")
    ax1.set_xlim(max(float(np.nanmax(rng)), 1.0) * 1.05, max(float(np.nanmin(rng)), 0.1) * 0.95)
    ax1.grid(alpha=0.3, which="both")
    fig.savefig(path)
    return path


def plot_contact(rec: EpisodeRecord, path: Path) -> Path:
    """Closing speed, lateral offset and speed, angular rate over the last metres vs the envelope."""
    e = rec.cfg.env.envelope
    z = rec.column("axial_distance").astype(float)
    sel = z <= max(5.0, float(np.nanmin(z)) + 1e-6)
    fig = _figure(10, 6)
    axes = fig.subplots(2, 2).ravel()
    spec = [
        ("closing_speed", "closing speed [m/s]", (e.axial_speed_min_m_s, e.axial_speed_max_m_s)),
        ("lateral_offset", "lateral offset [m]", (0.0, e.lateral_offset_max_m)),
        ("lateral_speed", "lateral speed [m/s]", (0.0, e.lateral_speed_max_m_s)),
        ("angular_rate_deg_s", "relative angular rate [deg/s]", (0.0, e.angular_rate_max_deg_s)),
    ]
    for ax, (col, label, (lo, hi)) in zip(axes, spec):
        v = rec.column(col).astype(float)
        ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label="capture envelope")
        ax.plot(z[sel], v[sel], "k-", lw=1)
        ax.plot(z[-1:], v[-1:], "o", color="tab:green" if lo <= v[-1] <= hi else "tab:red",
                label=f"final {v[-1]:.3g}")
        ax.set(xlabel="axial distance to the port [m]", ylabel=label)
        ax.invert_xaxis()
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"Contact conditions ({rec.result.outcome})")
    fig.savefig(path)
    return path


def write_report(record: EpisodeRecord, out_dir: str | Path, *, video: bool = True,
                 fps: int = 10, new: bool = False) -> dict[str, Path]:
    """Write the report folder of one recorded episode; returns name -> path of what was written.

    The folder is claimed for reports (:mod:`agents.outputs`): a new or empty folder, or one an
    earlier report wrote; with ``new`` (a time-stamped default name) it must not exist yet.

    Raises:
        OutputFolderError (a ValueError): ``out_dir`` may not be written (see above).
    """
    from agents.outputs import claim_folder, lock_folder

    out = claim_folder(out_dir, KIND, new=new)
    with lock_folder(out):
        return _write_files(record, out, video, fps)


def _write_files(record: EpisodeRecord, out: Path, video: bool, fps: int) -> dict[str, Path]:
    files: dict[str, Path] = {"config": save_config(record.cfg, out / "config.yaml")}
    s = summary_dict(record)
    for p in write_log(record.rows, out):
        files[p.name] = p
    files["trajectory"] = plot_trajectory(record, out / "trajectory.png")
    files["errors_vs_range"] = plot_errors(record, out / "errors_vs_range.png")
    files["modes"] = plot_modes(record, out / "modes.png")
    files["modes_range"] = plot_mode_ranges(record, out / "modes_range.png")
    files["contact"] = plot_contact(record, out / "contact.png")
    if video:
        v = write_video(record.frames, out, fps)
        if v is not None:
            files["video"] = v
    s["files"] = {k: p.name for k, p in files.items()}
    (out / "summary.json").write_text(json.dumps(json_safe(s), indent=2) + "\n")
    (out / "summary.txt").write_text(format_summary(s, out) + "\n")
    files["summary"] = out / "summary.json"
    return files
