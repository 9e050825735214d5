"""Offline replay: the TriDAR pipeline run again on recorded or real point clouds.

:func:`load_recording` reads a tridar-env MCAP (:mod:`tridar_env.recording`) into a list of
:class:`Item` (pipeline resets, external pose seeds and frames); :func:`real_data_items` makes the
same list from frames recorded elsewhere (:mod:`agents.replay_sources`). :func:`replay` builds a
pipeline from a mission config and feeds the items through ``TriDAR.step``:

* with the recorded settings (``exact``), each call starts from the recorded generator state and
  each scan hands back the recorded cloud and the generator state after it, so the state vectors
  equal the live ones bitwise (``ReplayResult.bitwise_equal`` counts them);
* with other settings, the frames are the recorded ones in time order: when the pipeline scans at
  ``t`` it gets the newest recorded cloud that started by ``t`` and was not used yet (or an empty
  frame), and its generator runs on its own.

The truth scene of a recording (pose and Sun direction) is passed along, so the simulated
coarse-range and thermal sensors, which read truth, behave as they did; for real data the clouds
themselves are the scene.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from perception.config import MissionConfig, flatten_overrides, resolve_config
from perception.pipeline.state import StateVector, TruthScene
from perception.sensing.pointcloud import PointCloud
from tridar_env.recording import set_rng_state, state_to_dict

FloatArray = npt.NDArray[np.float64]

__all__ = ["Item", "ReplayResult", "load_recording", "real_data_items", "replay"]


@dataclass
class Scan:
    """A recorded scan: the cloud and the generator state after it (None for real data)."""

    cloud: PointCloud
    rng: dict[str, Any] | None = None


@dataclass
class Item:
    """One pipeline input: ``kind`` ``reset`` (``rng``), ``seed_pose`` (``T``, ``t``) or
    ``frame`` (``t``, ``scans``, ``rng`` at the call, ``ego``, ``truth`` pose, ``sun``, the
    ``live`` state as recorded)."""

    kind: str
    t: float = 0.0
    rng: dict[str, Any] | None = None
    T: FloatArray | None = None
    scans: list[Scan] = field(default_factory=list)
    ego: Any = None
    truth: FloatArray | None = None
    sun: FloatArray | None = None
    live: dict[str, Any] | None = None


@dataclass
class Source:
    """What to replay: items, the mission config they were recorded with (or None) and a name."""

    items: list[Item]
    cfg: MissionConfig | None
    name: str
    problems: list[str] = field(default_factory=list)


def _cloud_from_msg(data: Any, scan: dict[str, Any]) -> PointCloud:
    from tridar_env.ros2msgs import cloud_arrays

    f = cloud_arrays(data)
    organized = valid = None
    if "grid" in scan:
        rows, cols = scan["grid"]
        valid = np.zeros(rows * cols, dtype=bool)
        valid[np.asarray(scan["valid_index"], dtype=np.int64)] = True
        organized = np.full((rows * cols, 3), np.nan)
        organized[valid] = np.column_stack([f["x"], f["y"], f["z"]])
        organized, valid = organized.reshape(rows, cols, 3), valid.reshape(rows, cols)
    return PointCloud(
        points=np.column_stack([f["x"], f["y"], f["z"]]), times=f["t"], subsystem=f["subsystem"],
        intensity=f["intensity"], sigma=f["sigma"], directions=np.column_stack([f["dx"], f["dy"], f["dz"]]),
        spurious=f["spurious"].astype(bool), organized=organized, valid_mask=valid,
        t_start=scan["t_start"], t_end=scan["t_end"],
    )


def load_recording(path: str | Path, warn: Callable[[str], None] | None = None) -> Source:
    """The pipeline inputs of a tridar-env recording (a damaged file keeps its good frames)."""
    from perception.pipeline.filter import EgoMotion
    from tridar_env.mcap_log import CONFIG_ATTACHMENT, read_mcap

    c = read_mcap(path, topics={"/tridar/points", "/tridar/frame", "/tridar/event"}, warn=warn)
    text = c.attachments.get(CONFIG_ATTACHMENT)
    cfg = MissionConfig.model_validate_json(text) if text else None
    clouds = {m.sequence: m.data for m in c.messages if m.topic == "/tridar/points"}
    items: list[Item] = []
    missing = 0
    for m in c.messages:
        d = m.data
        if m.topic == "/tridar/event":
            if d["kind"] == "reset":
                items.append(Item("reset", rng=d["rng"]))
            elif d["kind"] == "seed_pose":
                items.append(Item("seed_pose", t=float(d["t"]), T=np.array(d["T_sensor_target"])))
        elif m.topic == "/tridar/frame":
            scans = []
            for s in d["scans"]:
                msg = clouds.get(s["seq"])
                if msg is None:
                    missing += 1
                    continue
                scans.append(Scan(_cloud_from_msg(msg, s), s.get("rng")))
            if len(scans) < len(d["scans"]):
                continue  # a frame whose cloud was lost cannot be replayed exactly
            truth = d.get("truth")
            ego = d.get("ego")
            items.append(Item(
                "frame", t=float(d["t"]), rng=d["rng"], scans=scans,
                ego=None if ego is None else EgoMotion(
                    np.array(ego["omega"]), np.array(ego["accel"]),
                    None if ego.get("gravity_gradient") is None else np.array(ego["gravity_gradient"])),
                truth=None if truth is None else np.array(truth["T_sensor_target"]),
                sun=None if truth is None or truth["sun_direction_target"] is None
                else np.array(truth["sun_direction_target"]),
                live=d["state"],
            ))
    problems = list(c.problems)
    if missing:
        line = f"{path}: {missing} recorded clouds missing; their frames left out"
        problems.append(line)
        (warn or _stderr)(line)
    if not any(i.kind == "frame" for i in items):
        raise ValueError(f"{path}: no pipeline frames (/tridar/frame); expected a tridar-env recording "
                         "made with the TriDAR pipeline, or pass --topic for a PointCloud2 topic")
    return Source(items, cfg, str(path), problems)


def _stderr(line: str) -> None:
    import sys

    print(line, file=sys.stderr)


def real_data_items(clouds: list[PointCloud], times: list[float], truth: Any = None,
                    seed_pose: FloatArray | None = None) -> list[Item]:
    """Items for frames recorded elsewhere: a reset, an optional pose seed, then each cloud at its
    time (``truth``: a :class:`~agents.replay_sources.Truth` for the errors)."""
    items = [Item("reset")]
    if seed_pose is not None and times:
        items.append(Item("seed_pose", t=times[0], T=np.asarray(seed_pose, dtype=np.float64)))
    for cloud, t in zip(clouds, times):
        T = truth.at(t) if truth is not None else None
        items.append(Item("frame", t=t, scans=[Scan(cloud)], truth=T))
    return items


def resolve_replay_config(recorded: MissionConfig | None, mission: str | None,
                          overrides: dict[str, Any]) -> MissionConfig:
    """The config to replay with: the recorded one (or ``mission``) with ``overrides`` on top."""
    if mission is not None:
        return resolve_config(mission, overrides)
    if recorded is None:
        raise ValueError("no mission config: the source has none recorded; pass --mission")
    if not overrides:
        return recorded
    return resolve_config(None, {**flatten_overrides(recorded.model_dump(mode="json")), **overrides})


@dataclass
class ReplayResult:
    """The replayed state vectors and, per frame, the truth pose (or None) and the live state."""

    states: list[StateVector]
    truth: list[FloatArray | None]
    live: list[dict[str, Any] | None]
    exact: bool
    frames_processed: int
    frames_offered: int

    @property
    def bitwise_equal(self) -> int:
        """Frames whose replayed state equals the recorded one bit for bit."""
        return sum(1 for sv, lv in zip(self.states, self.live)
                   if lv is not None and _same(state_to_dict(sv), lv))

    @property
    def compared(self) -> int:
        return sum(1 for lv in self.live if lv is not None)

    def errors(self) -> dict[str, FloatArray]:
        """Per frame: ``t``, position error [m], attitude error [deg] (NaN without a pose or
        truth), protection level [m], pose validity, mode."""
        from perception.geometry import fast_quat_to_matrix

        n = len(self.states)
        pe, ae = np.full(n, np.nan), np.full(n, np.nan)
        for i, (sv, T) in enumerate(zip(self.states, self.truth)):
            if T is None:
                continue
            if sv.valid.position:
                pe[i] = float(np.linalg.norm(sv.position - T[:3, 3]))
            if sv.valid.attitude:
                tr = float(np.sum(T[:3, :3] * fast_quat_to_matrix(sv.quaternion)))
                ae[i] = math.degrees(math.acos(min(max((tr - 1.0) / 2.0, -1.0), 1.0)))
        return {
            "t": np.array([sv.t for sv in self.states]), "pos_err_m": pe, "att_err_deg": ae,
            "protection_level_m": np.array([sv.protection_level for sv in self.states]),
            "pose_valid": np.array([sv.valid.pose for sv in self.states]),
            "mode": np.array([int(sv.mode) for sv in self.states]),
        }


def _same(a: dict[str, Any], b: dict[str, Any]) -> bool:
    # JSON text: float repr is exact and tells -0.0 from 0.0.
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _make_pipeline(cfg: MissionConfig) -> Any:
    from tridar_env.env import make_target

    target = make_target(cfg)
    if cfg.env.perception == "flash":
        from perception.pipeline.flash import FlashPipeline

        return FlashPipeline(cfg, target)
    from perception.pipeline import TriDAR

    return TriDAR(cfg, target)


def _generator(state: dict[str, Any] | None, seed: int = 0) -> np.random.Generator:
    if state is None:
        return np.random.default_rng(seed)
    bit_gen = getattr(np.random, str(state.get("bit_generator", "PCG64")))
    rng = np.random.Generator(bit_gen())
    set_rng_state(rng, state)
    return rng


class _Feeder:
    """The pipeline's ``scan`` during a replay: recorded clouds instead of the sensor."""

    def __init__(self, pipe: Any, items: list[Item], exact: bool) -> None:
        self.pipe, self.exact = pipe, exact
        self.queue = [s for it in items if it.kind == "frame" for s in it.scans]
        self.queue.sort(key=lambda s: s.cloud.t_start)
        self.next = 0  # first queue entry not handed out
        self.frame: list[Scan] = []
        pipe.scan = self.scan

    def scan(self, scene: Any, t: float, pattern: Any) -> PointCloud:
        if self.exact and self.frame:
            s = self.frame.pop(0)
            if s.rng is not None:
                set_rng_state(self.pipe.rng, s.rng)
            return s.cloud
        # The newest recorded cloud that started by t and was not used; older ones are skipped.
        best = None
        while self.next < len(self.queue) and self.queue[self.next].cloud.t_start <= t + 1e-9:
            best = self.queue[self.next]
            self.next += 1
        if best is None:
            return PointCloud.empty(t)
        return best.cloud


def replay(items: list[Item], cfg: MissionConfig, *, exact: bool = False,
           on_frame: Callable[[int], None] | None = None) -> ReplayResult:
    """Run the pipeline of ``cfg`` on ``items`` (see the module docstring).

    Args:
        items: from :func:`load_recording` or :func:`real_data_items`.
        cfg: the mission config to build the pipeline from.
        exact: restore the recorded generator states (the recorded settings; bitwise replay).
        on_frame: progress callback with the frame index.
    """
    pipe = _make_pipeline(cfg)
    recorded = any(it.kind == "frame" and it.rng is not None for it in items)
    feeder = _Feeder(pipe, items, exact and recorded) if recorded else None
    states: list[StateVector] = []
    truth: list[FloatArray | None] = []
    live: list[dict[str, Any] | None] = []
    offered = 0
    for it in items:
        if it.kind == "reset":
            pipe.reset(_generator(it.rng if exact else None))
            pipe.prepare()
        elif it.kind == "seed_pose":
            pipe.seed_pose(it.T, it.t)
        elif it.kind == "frame":
            offered += 1
            if feeder is not None:
                if exact and it.rng is not None:
                    set_rng_state(pipe.rng, it.rng)
                feeder.frame = list(it.scans)
            scene: TruthScene | PointCloud
            if it.truth is not None and feeder is not None:
                scene = TruthScene(it.truth, it.t, None, sun_direction_target=it.sun)
            elif it.scans:
                scene = it.scans[0].cloud
            else:
                scene = PointCloud.empty(it.t)
            states.append(pipe.step(scene, it.t, ego=it.ego))
            truth.append(it.truth)
            live.append(it.live if exact else None)
            if on_frame is not None:
                on_frame(len(states))
    return ReplayResult(states, truth, live, exact and recorded, pipe.stats.frames, offered)


def summary_rows(res: ReplayResult) -> list[dict[str, Any]]:
    """One table row per quantity: median, p90 and max over frames with a pose and truth."""
    e = res.errors()
    rows = []
    for key, unit in (("pos_err_m", "m"), ("att_err_deg", "deg"), ("protection_level_m", "m")):
        v = e[key][np.isfinite(e["pos_err_m"])] if key == "protection_level_m" else e[key]
        v = v[np.isfinite(v)]
        rows.append({"quantity": key, "unit": unit, "n": int(v.size),
                     "median": float(np.median(v)) if v.size else math.nan,
                     "p90": float(np.percentile(v, 90)) if v.size else math.nan,
                     "max": float(v.max()) if v.size else math.nan})
    return rows


def plot_errors(res: ReplayResult, path: str | Path, title: str = "") -> Path:
    """Errors, protection level and mode against time, one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = res.errors()
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    ax[0].plot(e["t"], e["pos_err_m"], ".", ms=3, label="position error")
    ax[0].plot(e["t"], np.where(np.isfinite(e["pos_err_m"]), e["protection_level_m"], np.nan), "-",
               lw=1, label="protection level")
    ax[0].set_ylabel("[m]")
    ax[0].set_yscale("log")
    ax[0].legend(loc="upper right")
    ax[1].plot(e["t"], e["att_err_deg"], ".", ms=3, color="tab:red")
    ax[1].set_ylabel("attitude error [deg]")
    ax[2].step(e["t"], e["mode"], where="post")
    ax[2].set_yticks([0, 1, 2], ["bearing", "search", "tracking"])
    ax[2].set_xlabel("t [s]")
    fig.suptitle(title or "replay")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
