"""Flying run specs: one in a worker (:func:`run_one`), many serially or on Dask (:func:`iter_results`).

Shared by campaigns (:mod:`agents.campaign`) and policy evaluation (:mod:`agents.evaluation`): a
:class:`~agents.campaign_spec.RunSpec` goes in, one results row comes out (the episode's summary,
its dispersed values as ``disp__<key>`` columns and a thinned estimation-error trace). The
execution is an embedded ``LocalCluster`` (processes, one single-threaded worker per core), an
existing scheduler (``tcp://host:port``, whose workers must have tridar-env installed), or a plain
loop in this process; a run's row is the same on any of them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from agents.campaign_spec import RunSpec, bare_id
from perception.config import config_path, load_config

__all__ = ["TRACE_POINTS", "episode_row", "iter_results", "make_env", "open_client", "run_one"]

log = logging.getLogger(__name__)

#: Steps of the per-run estimation-error trace kept for the error-vs-range plot.
TRACE_POINTS = 100
#: Environment variable naming the folder where each run records ``run-<index>.mcap``
#: (``tridar-env campaign --record``; workers of the embedded cluster inherit it).
RECORD_DIR_ENV = "TRIDAR_ENV_RECORD_DIR"


# ---------------------------------------------------------------------------------------------
# One run (executed in a worker)
# ---------------------------------------------------------------------------------------------
def make_env(
    env_id: str, perception: str, overrides: dict[str, Any] | None = None, mission: str | None = None
) -> Any:
    """``gym.make`` with config overrides, honouring an overridden ``max_episode_steps``.

    Args:
        env_id: registered id, with or without the ``tridar_env:`` prefix.
        perception: ``truth`` | ``truth+noise`` | ``tridar``.
        overrides: ``__``-nested mission-config overrides.
        mission: a mission YAML to use instead of the id's own file.
    """
    import gymnasium as gym

    import tridar_env  # noqa: F401  (registers the ids)
    from tridar_env.registration import ENV_IDS

    ov = {k: v for k, v in (overrides or {}).items() if k.replace(".", "__") != "env__perception"}
    path = mission or config_path(ENV_IDS[bare_id(env_id)])
    steps = load_config(path, **ov, env__perception=perception).env.max_episode_steps
    return gym.make(
        bare_id(env_id), perception=perception, config=mission, max_episode_steps=steps, **ov
    )


def episode_row(result: Any) -> dict[str, Any]:
    """A results row from an :class:`agents.episode.EpisodeResult` (without index and traces).

    ``outcome`` is ``docked`` or ``failed``; ``cause`` is the termination cause (``docked``,
    ``collision``, ``out_of_bounds``, ``out_of_fuel``, ``corridor_exit``, ``timeout``; for a
    fly-around ``completed`` or ``keep_out``); ``success`` is docked or completed.
    """
    r = result.row()
    env_seed_ = r.pop("seed")
    cause = r.pop("outcome")
    from agents.episode import SUCCESS_CAUSES

    return {
        "outcome": "docked" if cause == "docked" else "failed",
        "cause": cause,
        "docked": cause == "docked",
        "success": cause in SUCCESS_CAUSES,
        "env_seed": int(env_seed_),
        **r,
    }


def _traces(result: Any) -> dict[str, list[float]]:
    rng_ = np.asarray(result.log.get("range_true", []), dtype=np.float64)
    pe = np.asarray(result.log.get("est_pos_err_m", []), dtype=np.float64)
    ae = np.asarray(result.log.get("est_att_err_deg", []), dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(pe))
    if ok.size > TRACE_POINTS:
        ok = ok[np.linspace(0, ok.size - 1, TRACE_POINTS).round().astype(int)]
    return {
        "trace_range_m": rng_[ok].tolist(),
        "trace_pos_err_m": pe[ok].tolist(),
        "trace_att_err_deg": ae[ok].tolist(),
    }


def _disp_columns(dispersed: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in dispersed.items():
        if isinstance(v, bool) or v is None or isinstance(v, str):
            out[f"disp__{k}"] = v if not isinstance(v, bool) else float(v)
        elif isinstance(v, (int, float)):
            out[f"disp__{k}"] = float(v)
        else:
            out[f"disp__{k}"] = json.dumps(v)
    return out


def run_one(spec: RunSpec) -> dict[str, Any]:
    """Fly one run and return its row; never raises (an exception becomes outcome ``error``).

    Top-level and import-light so that Dask can ship it to any worker.
    """
    from agents.controllers import make_controller
    from agents.episode import run_episode

    t0 = time.perf_counter()
    head = {"index": spec.index, "env_seed": spec.env_seed}
    try:
        env = make_env(spec.env_id, spec.perception, spec.overrides, spec.mission)
        record_dir = os.environ.get(RECORD_DIR_ENV)
        if record_dir:  # campaign --record: this run's MCAP (a file of that folder's, replaced)
            from tridar_env.recording import RecordMCAP

            env = RecordMCAP(env, os.path.join(record_dir, f"run-{spec.index:06d}.mcap"), force=True,
                             label=f"{spec.env_id} run {spec.index} seed {spec.env_seed}")
        try:
            ctrl = make_controller(spec.controller, env.unwrapped.cfg)
            res = run_episode(env, ctrl, spec.env_seed, keep_log=True, max_steps=spec.max_steps)
        finally:
            env.close()
        row = {**head, **episode_row(res), **_traces(res)}
    except Exception as exc:  # noqa: BLE001  (a crashed run is a result too; the campaign goes on)
        row = {
            **head, "outcome": "error", "cause": f"{type(exc).__name__}: {exc}"[:500],
            "docked": False, "success": False, "trace_range_m": [], "trace_pos_err_m": [], "trace_att_err_deg": [],
        }
    row.update(_disp_columns(spec.dispersed))
    row["wall_time_s"] = time.perf_counter() - t0
    return row


# ---------------------------------------------------------------------------------------------
# Executors
# ---------------------------------------------------------------------------------------------
@contextlib.contextmanager
def open_client(
    scheduler: str | None = None, workers: int | None = None, connect_timeout_s: float = 10.0
) -> Iterator[Any]:
    """A Dask client on an embedded LocalCluster (default) or on ``scheduler``.

    Args:
        scheduler: ``tcp://host:port`` of a running scheduler, or None for a LocalCluster.
        workers: LocalCluster worker processes (default: one per core).
        connect_timeout_s: give up on an unreachable scheduler after this long.

    Raises:
        ValueError: the scheduler cannot be reached (one line naming the address).
    """
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=f"{connect_timeout_s}s")
        except Exception as exc:  # noqa: BLE001  (any failure to connect is one error line)
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ValueError(
                f"cannot reach the Dask scheduler at {scheduler!r} within {connect_timeout_s:g} s "
                f"({reason}); expected a running scheduler such as tcp://host:8786"
            ) from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers or os.cpu_count() or 1
    # Workers' logs are silenced below CRITICAL: a run's own failure comes back as its row, and
    # closing the cluster under load (SIGTERM, Ctrl-C) made a worker whose heartbeat met the
    # closed scheduler print a traceback (ERROR) after the one-line exit message.
    cluster = LocalCluster(
        n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
        silence_logs=logging.CRITICAL,
    )
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def _task_key(spec: RunSpec) -> str:
    # Content-addressed: two campaigns sharing a scheduler never share a key by accident.
    digest = hashlib.sha1(
        json.dumps(asdict(spec), sort_keys=True, default=str).encode()
    ).hexdigest()[:16]
    return f"tridar-run-{spec.index:06d}-{digest}"


def iter_results(specs: Sequence[RunSpec], client: Any | None = None) -> Iterator[dict[str, Any]]:
    """Rows of ``specs`` as they finish: on ``client`` (Dask), or serially in this process.

    Futures still pending when the consumer stops (an interruption) are cancelled.
    """
    if client is None:
        for spec in specs:
            yield run_one(spec)
        return
    from dask.distributed import as_completed

    futures = [client.submit(run_one, s, key=_task_key(s), pure=False) for s in specs]
    try:
        for fut in as_completed(futures):
            try:
                row = fut.result()
            except Exception as exc:  # noqa: BLE001  (a dead worker: nothing is written, rerun retries)
                log.warning("a run failed to execute: %s", exc)
                continue
            fut.release()
            yield row
    finally:
        client.cancel([f for f in futures if not f.done()])
