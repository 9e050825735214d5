"""Record a run to MCAP: the :class:`RecordMCAP` Gymnasium wrapper and the pipeline's tap.

``RecordMCAP(env, "run.mcap")`` writes every episode the env flies (topics in
:mod:`tridar_env.mcap_log`). With the TriDAR pipeline in the loop a :class:`PipelineTap` records,
for every call of ``TriDAR.step``, what the pipeline consumed and what it published:

* the call time, the host's ego-motion (when given) and the truth scene's pose and Sun direction
  (the simulated coarse-range and thermal sensors read them);
* every cloud it scanned (``/tridar/points``) with its frame times and scan window;
* the state of its random generator when the call started and after each scan (the PAH search
  draws from it), so that a replay continues exactly where the live run was;
* the ``StateVector`` it returned, at full precision (JSON numbers round-trip float64).

From that a replay (:mod:`agents.replay`) rebuilds the same pipeline from the recorded config and
gets bitwise the same state vectors. The tap does not touch the simulation: it wraps the
pipeline's bound methods on the instance and passes every argument and result through.

Recording costs one copy of each cloud into a packed buffer, a few small JSON messages per frame
and LZ4 compression of 1 MB chunks (a file cut short loses at most its last chunk);
``tridar-env bench record`` measures it.
"""

from __future__ import annotations

import base64
import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from perception.pipeline.state import Mode, StateVector, TruthScene, Validity
from perception.sensing.pointcloud import PointCloud
from tridar_env.mcap_log import CONFIG_ATTACHMENT, METADATA_NAME, McapLog, time_ns
from tridar_env.ros2msgs import pointcloud2, pose_stamped, pose_with_covariance_stamped

__all__ = ["PipelineTap", "RecordMCAP", "rng_state", "set_rng_state", "state_from_dict", "state_to_dict"]

_BIG = 2**53
_ARRAYS = ("position", "velocity", "quaternion", "angular_velocity", "bearing")


# ---------------------------------------------------------------------------------- serialisation
def _ints_as_hex(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _ints_as_hex(v) for k, v in o.items()}
    if isinstance(o, int) and not isinstance(o, bool) and abs(o) >= _BIG:
        return hex(o)  # exact in JSON (a JSON number this large is not, in most readers)
    return o


def _hex_as_ints(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _hex_as_ints(v) for k, v in o.items()}
    if isinstance(o, str) and o.startswith(("0x", "-0x")):
        return int(o, 16)
    return o


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """The generator's bit-generator state as JSON-safe data (big integers as hex strings)."""
    st = rng.bit_generator.state
    inner = st.get("state")
    if st.get("bit_generator") == "PCG64" and isinstance(inner, dict):  # the default: no recursion
        return {**st, "state": {"state": hex(inner["state"]), "inc": hex(inner["inc"])}}
    return _ints_as_hex(st)


def set_rng_state(rng: np.random.Generator, state: dict[str, Any]) -> None:
    """Restore a state from :func:`rng_state` (the bit generator must be of the same kind)."""
    rng.bit_generator.state = _hex_as_ints(state)


_VALID_FIELDS = tuple(f.name for f in dataclasses.fields(Validity))


def _valid_dict(v: Validity) -> dict[str, bool]:
    return {name: getattr(v, name) for name in _VALID_FIELDS}  # dataclasses.asdict deep-copies


def state_to_dict(sv: StateVector) -> dict[str, Any]:
    """Every field of a ``StateVector`` as JSON-safe data (exact: floats round-trip; the (12, 12)
    covariance is base64 of its little-endian float64 bytes, a sixth of the cost of 144 numbers)."""
    d: dict[str, Any] = {
        "t": sv.t, "mode": int(sv.mode), "mode_name": Mode(sv.mode).name.lower(),
        "valid": _valid_dict(sv.valid),
        "covariance_f8le_b64": base64.b64encode(sv.covariance.astype("<f8").tobytes()).decode(),
    }
    for name in _ARRAYS:
        d[name] = getattr(sv, name).tolist()
    for name in ("range", "range_rate", "fitness", "latency", "protection_level", "alert_limit"):
        d[name] = float(getattr(sv, name))
    d["n_points"] = int(sv.n_points)
    d["bearing_source"] = sv.bearing_source
    return d


def state_from_dict(d: dict[str, Any]) -> StateVector:
    """The ``StateVector`` of :func:`state_to_dict`."""
    kw = {name: np.array(d[name], dtype=np.float64) for name in _ARRAYS}
    return StateVector(
        t=float(d["t"]), mode=Mode(int(d["mode"])), valid=Validity(**d["valid"]),
        covariance=np.frombuffer(base64.b64decode(d["covariance_f8le_b64"]), dtype="<f8").reshape(12, 12),
        range=float(d["range"]), range_rate=float(d["range_rate"]), fitness=float(d["fitness"]),
        n_points=int(d["n_points"]), latency=float(d["latency"]),
        protection_level=float(d["protection_level"]), alert_limit=float(d["alert_limit"]),
        bearing_source=str(d["bearing_source"]), **kw,
    )


def _state_summary(sv: StateVector) -> dict[str, Any]:
    """The small, plottable view of a state (``/tridar/state``)."""
    return {
        "t": sv.t, "mode": Mode(sv.mode).name.lower(), "valid": _valid_dict(sv.valid),
        "pose_valid": sv.valid.pose, "protection_level": sv.protection_level,
        "alert_limit": sv.alert_limit, "range": sv.range, "range_rate": sv.range_rate,
        "fitness": sv.fitness, "n_points": sv.n_points, "latency": sv.latency,
        "bearing": sv.bearing.tolist(), "bearing_source": sv.bearing_source,
    }


def _scan_region(pattern: Any, mode: str, t: float) -> dict[str, Any]:
    az, el = getattr(pattern, "az", None), getattr(pattern, "el", None)
    out: dict[str, Any] = {"t": t, "mode": mode, "pattern": str(getattr(pattern, "name", ""))}
    if az is not None and el is not None and len(az):
        out.update(az_min=float(np.min(az)), az_max=float(np.max(az)), el_min=float(np.min(el)),
                   el_max=float(np.max(el)), samples=len(az))
    return out


# ---------------------------------------------------------------------------------- the tap
class PipelineTap:
    """Records what a TriDAR pipeline consumes and publishes (see the module docstring).

    Args:
        pipeline: a ``perception.pipeline.TriDAR`` (or its flash form).
        log: the open recording.
        clock: ``t -> log time [ns]`` (the wrapper adds the episode's offset).
    """

    def __init__(self, pipeline: Any, log: McapLog, clock: Any) -> None:
        self.pipeline = pipeline
        self.log = log
        self.clock = clock
        self._orig = {name: getattr(pipeline, name) for name in ("step", "scan", "reset", "seed_pose")}
        self._frame: dict[str, Any] | None = None
        pipeline.step = self._step
        pipeline.scan = self._scan
        pipeline.reset = self._reset
        pipeline.seed_pose = self._seed_pose

    def detach(self) -> None:
        """Give the pipeline its own methods back."""
        for name in self._orig:
            self.pipeline.__dict__.pop(name, None)

    def _reset(self, rng: np.random.Generator) -> None:
        self._orig["reset"](rng)
        self.log.json("/tridar/event", {"kind": "reset", "t": 0.0, "rng": rng_state(rng)}, self.clock(0.0))

    def _seed_pose(self, T_sensor_target: Any, t: float) -> None:
        self._orig["seed_pose"](T_sensor_target, t)
        T = np.asarray(T_sensor_target, dtype=np.float64)
        self.log.json("/tridar/event", {"kind": "seed_pose", "t": float(t), "T_sensor_target": T.tolist()},
                      self.clock(float(t)))

    def _scan(self, scene: Any, t: float, pattern: Any) -> PointCloud:
        cloud = self._orig["scan"](scene, t, pattern)
        t0 = time.process_time()
        tns = self.clock(float(t))
        msg = pointcloud2(cloud.points, cloud.times, cloud.intensity, cloud.sigma, cloud.directions,
                          cloud.subsystem, cloud.spurious, float(cloud.t_start))
        seq = self.log.ros("/tridar/points", "sensor_msgs/msg/PointCloud2", msg, tns)
        scan: dict[str, Any] = {"seq": seq, "t_start": float(cloud.t_start), "t_end": float(cloud.t_end),
                                "rng": rng_state(self.pipeline.rng)}
        if cloud.organized is not None:
            scan["grid"] = list(cloud.organized.shape[:2])
            scan["valid_index"] = np.flatnonzero(cloud.valid_mask.reshape(-1)).tolist()
        if self._frame is not None:
            self._frame["scans"].append(scan)
        mode = Mode(self.pipeline.mode).name.lower()
        self.log.json("/tridar/scan_region", _scan_region(pattern, mode, float(t)), tns)
        self.log.busy_s += time.process_time() - t0
        return cloud

    def _step(self, scene: Any, t: float, ego: Any = None) -> StateVector:
        t0 = time.process_time()
        frame: dict[str, Any] = {"t": float(t), "rng": rng_state(self.pipeline.rng), "scans": []}
        if ego is not None:
            frame["ego"] = {"omega": np.asarray(ego.omega).tolist(), "accel": np.asarray(ego.accel).tolist()}
            if ego.gravity_gradient is not None:
                frame["ego"]["gravity_gradient"] = np.asarray(ego.gravity_gradient).tolist()
        truth = None
        if isinstance(scene, TruthScene):
            truth = np.asarray(scene.T_sensor_target, dtype=np.float64)
            sun = scene.sun_direction_target
            frame["truth"] = {
                "t": float(scene.t), "T_sensor_target": truth.tolist(),
                "sun_direction_target": None if sun is None else np.asarray(sun).tolist(),
            }
        self._frame = frame
        self.log.busy_s += time.process_time() - t0
        try:
            sv = self._orig["step"](scene, t, ego)
        finally:
            self._frame = None
        t0 = time.process_time()
        frame["state"] = state_to_dict(sv)
        tns = self.clock(float(t))
        self.log.json("/tridar/frame", frame, tns)
        write_state(self.log, sv, tns, truth)
        self.log.busy_s += time.process_time() - t0
        return sv


def write_state(log: McapLog, sv: StateVector, tns: int, T_truth: np.ndarray | None) -> None:
    """``/tridar/state``, ``/tridar/estimate`` (with a pose) and ``/truth/pose`` (with truth)."""
    log.json("/tridar/state", _state_summary(sv), tns)
    if sv.valid.position and sv.valid.attitude:
        log.ros("/tridar/estimate", "geometry_msgs/msg/PoseWithCovarianceStamped",
                pose_with_covariance_stamped(sv.t, sv.position, sv.quaternion, sv.covariance), tns)
    if T_truth is not None:
        from perception.geometry import fast_matrix_to_quat

        log.ros("/truth/pose", "geometry_msgs/msg/PoseStamped",
                pose_stamped(sv.t, T_truth[:3, 3], fast_matrix_to_quat(T_truth[:3, :3])), tns)


# ---------------------------------------------------------------------------------- the wrapper
def _num(x: Any) -> Any:
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, np.ndarray):
        return [_num(v) for v in x.reshape(-1).tolist()] if x.ndim <= 1 else [_num(r) for r in x]
    if isinstance(x, (list, tuple)):
        return [_num(v) for v in x]
    return x


class RecordMCAP(gym.Wrapper):
    """Record every episode of a ``DockingEnv`` (any wrapper around one) to an MCAP file.

    Args:
        env: the env to record.
        path: the ``.mcap`` file to create; an existing file is refused unless ``force``.
        force: replace an existing file.
        label: what the run was (an env id, a mission file), stored in the metadata.
        compression: of the file's chunks: ``lz4``, ``zstd`` or ``none`` (:class:`McapLog`).

    Example:
        >>> import gymnasium as gym, tridar_env
        >>> from tridar_env.recording import RecordMCAP
        >>> env = RecordMCAP(gym.make("TriDAR/FinalApproach-v0"), "run.mcap")  # doctest: +SKIP
    """

    def __init__(self, env: gym.Env, path: str | Path, *, force: bool = False, label: str = "",
                 compression: str = "lz4") -> None:
        super().__init__(env)
        u = env.unwrapped
        cfg = u.cfg
        self.log = McapLog(path, force=force, compression=compression)
        self.path = self.log.path
        from importlib.metadata import PackageNotFoundError, version

        try:
            ver = version("tridar-env")
        except PackageNotFoundError:  # pragma: no cover - a source tree without install
            ver = "unknown"
        self.log.metadata(METADATA_NAME, {
            "format": "tridar-env recording 1", "tridar_env_version": ver, "label": label,
            "perception": cfg.env.perception, "target": str(cfg.target.name),
            "frame_period_s": repr(cfg.env.frame_period_s),
        })
        self.log.attachment(CONFIG_ATTACHMENT, "application/json", cfg.model_dump_json(indent=1))
        self._offset = 0.0  # [s] of the current episode in the file
        self._t_end = 0.0
        self._episode = -1
        self._steps = 0
        observer = getattr(u, "observer", None)
        pipeline = getattr(observer, "pipeline", None)
        self.tap = PipelineTap(pipeline, self.log, self._clock) if pipeline is not None else None

    def _clock(self, t: float) -> int:
        self._t_end = max(self._t_end, self._offset + t)
        return time_ns(self._offset + t)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        if self._episode >= 0:
            self._offset = math.ceil(self._t_end + 1.0)  # the next episode starts a second later
        self._episode += 1
        self._steps = 0
        self.log.json("/tridar/event", {"kind": "episode", "t": 0.0, "episode": self._episode,
                                        "seed": seed, "offset_s": self._offset}, self._clock(0.0))
        obs, info = self.env.reset(seed=seed, options=options)
        self._record_step(info, None, None, False, False)
        return obs, info

    def step(self, action: Any) -> Any:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps += 1
        self._record_step(info, action, reward, terminated, truncated)
        return obs, reward, terminated, truncated, info

    def _record_step(self, info: dict[str, Any], action: Any, reward: Any, terminated: bool,
                     truncated: bool) -> None:
        t0 = time.process_time()
        u = self.env.unwrapped
        t = float(info.get("t", getattr(u.world, "t", 0.0)))
        tns = self._clock(t)
        w = u.world
        # World state and frames are finite (the world checks them); only the extras may be NaN.
        msg = {
            "episode": self._episode, "step": self._steps, "t": t,
            "action": None if action is None else _num(np.asarray(action, dtype=np.float64)),
            "reward": None if reward is None else _num(float(reward)),
            "reward_terms": {k[7:]: _num(v) for k, v in info.items() if k.startswith("reward_")},
            "terminated": bool(terminated), "truncated": bool(truncated),
            "termination": info.get("termination", ""), "mode": info.get("mode", ""),
            "r_lvlh": w.state[:3].tolist(), "v_lvlh": w.state[3:].tolist(),
            "pos_err_m": _num(info.get("estimate_position_error_m", math.nan)),
            "att_err_deg": _num(info.get("estimate_attitude_error_deg", math.nan)),
            "propellant_kg": _num(info.get("propellant_kg", math.nan)),
        }
        self.log.json("/env/step", msg, tns)
        if self.tap is None and u.state_vector is not None:  # truth perception: one state per step
            T = info.get("truth_T_sensor_target")
            write_state(self.log, u.state_vector, tns, None if T is None else np.asarray(T))
        self.log.busy_s += time.process_time() - t0

    def close(self) -> None:
        try:
            if self.tap is not None:
                self.tap.detach()
            self.log.close()
        finally:
            super().close()
