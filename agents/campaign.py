"""Monte Carlo campaigns: N closed-loop runs over dispersions, executed with Dask.

A campaign YAML (``configs/campaigns/*.yaml``, model :class:`CampaignConfig`) names an env id, a
perception mode, a controller, the number of runs, a campaign seed, constant config overrides and
**dispersions**: mission-config fields (``__``-nested, as for ``load_config``) mapped to a
distribution that is sampled once per run::

    dispersions:
      env__initial__range_m: {uniform: [25.0, 35.0]}               # U(a, b)
      dynamics__target_attitude__spin_rate_deg_s: {normal: [2.0, 0.5], clip: [0.0, null]}
      sensor__faults__dropout_prob: [0.0, 0.02, 0.1]               # a list: pick one, uniformly
      dynamics__target_attitude__initial_rpy_deg: {uniform: [[-10, -10, -10], [10, 10, 10]]}
      pipeline__restart_period_s: 30.0                             # a constant

Spec forms: a constant; a list (uniform choice); or a mapping with one of ``uniform: [lo, hi]``,
``loguniform: [lo, hi]``, ``normal: [mu, sigma]``, ``choice: [...]`` (+ optional ``weights``),
``constant: x``, and an optional ``clip: [lo, hi]`` (``null`` = unbounded) for the numeric ones.
Bounds may be lists (vector fields are sampled element-wise).

Reproducibility: run ``i`` of a campaign with seed ``s`` takes its randomness from
``SeedSequence(s, spawn_key=(i, ...))`` (exactly what ``SeedSequence(s).spawn`` would hand its i-th
child), one stream per dispersion key and one for the env reset seed, so a run is a function of
``(s, i)`` alone: the same on one core or a hundred, in any order, and adding a dispersion key does
not change the others' samples.

Execution: an embedded ``LocalCluster`` (processes, one single-threaded worker per core) by default,
or ``scheduler="tcp://host:port"`` for an existing cluster (whose workers must have tridar-env
installed), or an in-process serial loop. The client writes one Parquet part file per finished run
(``parts/run_000042.parquet``, written to a temporary name, fsynced and renamed), so an interrupted
campaign resumes from what exists and runs only the missing indices (a part that cannot be read
back is moved to ``parts/quarantine/`` and its run done again); the final ``results.parquet`` is
the union, one row per run. The resolved campaign config is saved as ``campaign.yaml`` beside the
results, and a resume refuses to mix results of a different config. The folder carries the marker
of :mod:`agents.outputs` and is locked while a campaign writes it.

Example:
    >>> from agents.campaign import load_campaign, run_campaign
    >>> cfg = load_campaign("configs/campaigns/final_approach_truth.yaml", runs=4)
    >>> res = run_campaign(cfg, "runs/campaign_demo")        # doctest: +SKIP
    >>> print(res.summary_table())                            # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agents.outputs import (
    atomic_write,
    check_folder,
    check_name,
    claim_folder,
    fsync_dir,
    is_marked,
    lock_folder,
    remove_stale_tmp,
)
from perception.config import (
    config_path,
    ConfigError,
    MissionConfig,
    load_config,
    save_config,
)

__all__ = [
    "CampaignConfig",
    "CampaignResult",
    "Dispersion",
    "RunSpec",
    "build_specs",
    "episode_row",
    "format_summary",
    "iter_results",
    "load_campaign",
    "make_env",
    "mission_config",
    "open_client",
    "plot_campaign",
    "run_campaign",
    "run_one",
    "run_seed_sequence",
    "summarize",
    "validate_campaign",
]

log = logging.getLogger(__name__)

_DIST_KEYS = ("uniform", "loguniform", "normal", "choice", "constant")
_DIST_EXTRA = {"clip", "weights"}
_PART_RE = re.compile(r"^run_(\d{6,})\.parquet$")
_QUARANTINED_RE = re.compile(r"^run_\d{6,}\.parquet(\.\d+)?$")
#: Marker kind of a campaign folder (:mod:`agents.outputs`).
KIND = "campaign"
#: Damaged parts are moved here (inside ``parts/``) on resume.
QUARANTINE_DIR = "quarantine"
_SUMMARY_FILES = ("results.parquet", "summary.json", "summary.txt")
PLOT_FILES = ("contact_envelope.png", "delta_v_hist.png", "error_vs_range.png")
#: Steps of the per-run estimation-error trace kept for the error-vs-range plot.
TRACE_POINTS = 100


# ---------------------------------------------------------------------------------------------
# Dispersions
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Dispersion:
    """One field's distribution (see the module docstring for the YAML forms).

    Attributes:
        kind: ``constant``, ``choice``, ``uniform``, ``loguniform`` or ``normal``.
        args: the distribution's parameters as given (bounds may be nested lists).
        weights: choice probabilities (normalised), or None for uniform choice.
        clip: ``(lo, hi)`` applied after sampling; None on a side means unbounded.
    """

    kind: str
    args: Any
    weights: tuple[float, ...] | None = None
    clip: tuple[float | None, float | None] | None = None

    @classmethod
    def parse(cls, key: str, spec: Any) -> Dispersion:
        """Read a YAML spec; errors name ``key``, the value and the accepted forms."""
        where = f"dispersions.{key}"
        if isinstance(spec, list):
            if not spec:
                raise ValueError(f"{where}: got an empty list; expected values to choose from")
            return cls("choice", list(spec))
        if not isinstance(spec, dict):
            return cls("constant", spec)
        kinds = [k for k in spec if k in _DIST_KEYS]
        if not kinds:
            # A mapping without a distribution key is a constant sub-config (e.g. an occluder).
            return cls("constant", spec)
        unknown = set(spec) - set(_DIST_KEYS) - _DIST_EXTRA
        if len(kinds) > 1 or unknown:
            raise ValueError(
                f"{where}: got {spec!r}; expected exactly one of {', '.join(_DIST_KEYS)} "
                f"with optional {sorted(_DIST_EXTRA)}"
            )
        kind = kinds[0]
        args = spec[kind]
        clip = spec.get("clip")
        weights = spec.get("weights")
        if kind == "constant":
            if clip is not None or weights is not None:
                raise ValueError(f"{where}: constant takes no clip or weights; got {spec!r}")
            return cls("constant", args)
        if kind == "choice":
            if not isinstance(args, list) or not args:
                raise ValueError(f"{where}.choice: got {args!r}; expected a non-empty list")
            w = None
            if weights is not None:
                if (
                    not isinstance(weights, list)
                    or len(weights) != len(args)
                    or any(not _is_number(x) or x < 0 for x in weights)
                    or sum(weights) <= 0
                ):
                    raise ValueError(
                        f"{where}.weights: got {weights!r}; expected {len(args)} non-negative "
                        "numbers with a positive sum"
                    )
                total = float(sum(weights))
                w = tuple(float(x) / total for x in weights)
            if clip is not None:
                raise ValueError(f"{where}: choice takes no clip; got clip={clip!r}")
            return cls("choice", list(args), weights=w)
        if weights is not None:
            raise ValueError(f"{where}: weights apply to choice only; got {spec!r}")
        if not isinstance(args, list) or len(args) != 2:
            raise ValueError(f"{where}.{kind}: got {args!r}; expected a list [a, b]")
        try:
            a = np.asarray(args[0], dtype=np.float64)
            b = np.asarray(args[1], dtype=np.float64)
            np.broadcast(a, b)
        except (TypeError, ValueError):
            raise ValueError(
                f"{where}.{kind}: got {args!r}; expected two numbers or two equal-length lists"
            ) from None
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ValueError(f"{where}.{kind}: got {args!r}; expected finite numbers")
        if kind in ("uniform", "loguniform") and np.any(a > b):
            raise ValueError(f"{where}.{kind}: got {args!r}; expected lower <= upper")
        if kind == "loguniform" and np.any(a <= 0):
            raise ValueError(f"{where}.loguniform: got {args!r}; expected positive bounds")
        if kind == "normal" and np.any(b < 0):
            raise ValueError(f"{where}.normal: got sigma {args[1]!r}; expected sigma >= 0")
        c = None
        if clip is not None:
            if (
                not isinstance(clip, list)
                or len(clip) != 2
                or any(v is not None and not _is_number(v) for v in clip)
            ):
                raise ValueError(f"{where}.clip: got {clip!r}; expected [lo, hi] (null = unbounded)")
            lo, hi = (None if v is None else float(v) for v in clip)
            if lo is not None and hi is not None and lo > hi:
                raise ValueError(f"{where}.clip: got {clip!r}; expected lo <= hi")
            c = (lo, hi)
        return cls(kind, [args[0], args[1]], clip=c)

    def extremes(self) -> list[Any]:
        """Values worth validating up front: bounds, clip limits or every choice."""
        if self.kind == "constant":
            return [self.args]
        if self.kind == "choice":
            return list(self.args)
        if self.kind == "normal":
            if self.clip is None:
                return []
            lo, hi = self.clip
            mu = np.asarray(self.args[0], dtype=np.float64)
            vals = [np.full_like(mu, v) for v in (lo, hi) if v is not None]
            return [float(v) if v.ndim == 0 else v.tolist() for v in vals]
        return [self.args[0], self.args[1]]

    def sample(self, rng: np.random.Generator) -> Any:
        """One draw (a plain Python value: float, list of floats, or the chosen item)."""
        if self.kind == "constant":
            return self.args
        if self.kind == "choice":
            i = int(rng.choice(len(self.args), p=self.weights))
            return self.args[i]
        a = np.asarray(self.args[0], dtype=np.float64)
        b = np.asarray(self.args[1], dtype=np.float64)
        shape = np.broadcast(a, b).shape
        if self.kind == "uniform":
            x = rng.uniform(a, b, size=shape)
        elif self.kind == "loguniform":
            x = np.exp(rng.uniform(np.log(a), np.log(b), size=shape))
        else:
            x = rng.normal(a, b, size=shape)
        if self.clip is not None:
            lo, hi = self.clip
            x = np.clip(x, -np.inf if lo is None else lo, np.inf if hi is None else hi)
        return float(x) if x.ndim == 0 else x.tolist()


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ---------------------------------------------------------------------------------------------
# Config
# ---------------------------------------------------------------------------------------------
class CampaignConfig(BaseModel):
    """A Monte Carlo campaign (one YAML file in ``configs/campaigns``).

    Attributes:
        name: label for tables and the default output folder ``runs/campaigns/<name>``: a plain
            folder name (letters, digits, ``.``, ``_``, ``-``; :func:`agents.outputs.check_name`).
        env_id: a registered id (``TriDAR/FinalApproach-v0``, ...).
        mission: optional mission YAML replacing the id's own mission file.
        perception: ``truth``, ``truth+noise`` or ``tridar``.
        controller: a name for :func:`agents.controllers.make_controller`.
        runs: number of runs (indices ``0 .. runs-1``).
        seed: campaign seed; run ``i`` depends on ``(seed, i)`` only.
        max_steps: optional cap on steps per run (outcome ``timeout`` when reached); the env's
            own ``max_episode_steps`` applies otherwise.
        config: constant mission-config overrides, ``__``-nested keys.
        dispersions: per-run sampled overrides (see the module docstring).
    """

    model_config = ConfigDict(extra="forbid")

    name: str = "campaign"
    env_id: str = "TriDAR/FinalApproach-v0"
    mission: str | None = None
    perception: Literal["truth", "truth+noise", "tridar"] = "tridar"
    controller: str = "glideslope"
    runs: Annotated[int, Field(ge=1, le=10_000_000)] = 100
    seed: Annotated[int, Field(ge=0)] = 0
    max_steps: Annotated[int, Field(ge=1)] | None = None
    config: dict[str, Any] = Field(default_factory=dict)
    dispersions: dict[str, Any] = Field(default_factory=dict)

    def dispersion_specs(self) -> dict[str, Dispersion]:
        """Parsed dispersions, in a stable (sorted) order."""
        return {k: Dispersion.parse(k, self.dispersions[k]) for k in sorted(self.dispersions)}

    def identity(self) -> dict[str, Any]:
        """What must match for results to be resumed or extended (all but ``runs``)."""
        d = self.model_dump(mode="json")
        d.pop("runs")
        return d


def _bare_id(env_id: str) -> str:
    return env_id.split(":", 1)[1] if ":" in env_id else env_id


def load_campaign(path: str | Path, **overrides: Any) -> CampaignConfig:
    """Read and validate a campaign YAML (``__``-nested overrides on top).

    A bare name such as ``final_approach_truth`` is looked up in ``configs/campaigns``. Besides
    the campaign's own fields, every ``config`` and ``dispersions`` key is checked against the
    mission config (run 0's sample and each dispersion's extremes), so a typo fails here and not in
    a worker.

    Raises:
        ConfigError: a missing or malformed file, or a field, value or key that does not validate.
    """
    p = config_path(path, "campaigns")
    cfg = load_config(p, model=CampaignConfig, **overrides)
    validate_campaign(cfg, str(p))
    return cfg


def validate_campaign(cfg: CampaignConfig, source: str = "campaign") -> None:
    """Check what pydantic cannot: the id, the controller name, the dispersion specs, and that
    the overrides and dispersions produce valid mission configs (run 0's sample and each
    dispersion's extremes), so that a typo fails here and not in a worker.

    Raises:
        ConfigError: naming the campaign, the field or key, and the offending value.
    """
    from agents.controllers import CONTROLLERS, controller_names
    from tridar_env.registration import ENV_IDS

    def fail(msg: str) -> None:
        raise ConfigError(f"campaign {source}: {msg}")

    try:
        check_name(cfg.name)
    except ValueError as exc:
        fail(str(exc))
    if _bare_id(cfg.env_id) not in ENV_IDS:
        fail(f"env_id={cfg.env_id!r} is not registered; expected one of {', '.join(ENV_IDS)}")
    if cfg.controller not in CONTROLLERS and ":" not in cfg.controller:
        fail(
            f"controller={cfg.controller!r} is unknown; expected one of "
            f"{', '.join(controller_names())}, 'sb3:<path>' or 'module:Class'"
        )
    if cfg.mission is not None and not Path(cfg.mission).is_file():
        fail(f"mission={cfg.mission!r}: no such file")
    overlap = sorted(set(cfg.config) & set(cfg.dispersions))
    if overlap:
        fail(f"keys {overlap} are both in config and in dispersions; expected each in one place")
    try:
        specs = cfg.dispersion_specs()
    except ValueError as exc:
        fail(str(exc))
    base = sample_overrides(cfg, 0)
    trials: list[tuple[str, dict[str, Any]]] = [("run 0", base)]
    for key, disp in specs.items():
        for value in disp.extremes():
            trials.append((f"dispersions.{key}={value!r}", {**base, key: value}))
    for what, ov in trials:
        try:
            mission_config(cfg, ov)
        except ConfigError as exc:
            detail = "; ".join(line.strip() for line in str(exc).splitlines()[1:]) or str(exc)
            fail(f"{what} gives an invalid mission: {detail}")


def mission_config(cfg: CampaignConfig, overrides: dict[str, Any] | None = None) -> MissionConfig:
    """The mission config of one run (the campaign's constants and ``overrides`` applied)."""
    from tridar_env.registration import ENV_IDS

    path = cfg.mission or config_path(ENV_IDS[_bare_id(cfg.env_id)])
    merged = {**cfg.config, **(overrides or {}), "env__perception": cfg.perception}
    return load_config(path, **merged)


# ---------------------------------------------------------------------------------------------
# Seeds and run specs
# ---------------------------------------------------------------------------------------------
def run_seed_sequence(campaign_seed: int, index: int) -> np.random.SeedSequence:
    """The seed sequence of run ``index``: ``SeedSequence(campaign_seed).spawn(n)[index]``."""
    return np.random.SeedSequence(campaign_seed, spawn_key=(index,))


def _key_stream(campaign_seed: int, index: int, key: str) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence(campaign_seed, spawn_key=(index, 0, zlib.crc32(key.encode())))
    )


def env_seed(campaign_seed: int, index: int) -> int:
    """Reset seed of run ``index`` (a non-negative 63-bit integer)."""
    ss = np.random.SeedSequence(campaign_seed, spawn_key=(index, 1))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def sample_overrides(cfg: CampaignConfig, index: int) -> dict[str, Any]:
    """The dispersed config overrides of run ``index`` (a function of ``(cfg.seed, index)``)."""
    return {
        key: disp.sample(_key_stream(cfg.seed, index, key))
        for key, disp in cfg.dispersion_specs().items()
    }


@dataclass(frozen=True)
class RunSpec:
    """Everything one worker needs to fly run ``index`` (small and picklable).

    Attributes:
        index: run index in the campaign.
        env_seed: reset seed.
        env_id: Gymnasium id (the ``tridar_env:`` prefix is added so workers register the ids).
        mission: mission YAML or None for the id's own.
        perception: perception mode.
        controller: controller name.
        overrides: constant and dispersed config overrides.
        dispersed: the sampled values only (they become ``disp__<key>`` columns).
        max_steps: step cap or None.
    """

    index: int
    env_seed: int
    env_id: str
    mission: str | None
    perception: str
    controller: str
    overrides: dict[str, Any]
    dispersed: dict[str, Any]
    max_steps: int | None


def build_specs(cfg: CampaignConfig, indices: Sequence[int] | None = None) -> list[RunSpec]:
    """Run specs for ``indices`` (default: all ``cfg.runs``)."""
    idx = range(cfg.runs) if indices is None else indices
    env_id = cfg.env_id if ":" in cfg.env_id else f"tridar_env:{cfg.env_id}"
    specs = []
    for i in idx:
        disp = sample_overrides(cfg, i)
        specs.append(
            RunSpec(
                index=int(i), env_seed=env_seed(cfg.seed, i), env_id=env_id, mission=cfg.mission,
                perception=cfg.perception, controller=cfg.controller,
                overrides={**cfg.config, **disp}, dispersed=disp, max_steps=cfg.max_steps,
            )
        )
    return specs


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
    path = mission or config_path(ENV_IDS[_bare_id(env_id)])
    steps = load_config(path, **ov, env__perception=perception).env.max_episode_steps
    return gym.make(
        _bare_id(env_id), perception=perception, config=mission, max_episode_steps=steps, **ov
    )


def episode_row(result: Any) -> dict[str, Any]:
    """A results row from an :class:`agents.episode.EpisodeResult` (without index and traces).

    ``outcome`` is ``docked`` or ``failed``; ``cause`` is the termination cause (``docked``,
    ``collision``, ``out_of_bounds``, ``out_of_fuel``, ``corridor_exit``, ``timeout``).
    """
    r = result.row()
    env_seed_ = r.pop("seed")
    cause = r.pop("outcome")
    return {
        "outcome": "docked" if cause == "docked" else "failed",
        "cause": cause,
        "docked": cause == "docked",
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
        try:
            ctrl = make_controller(spec.controller, env.unwrapped.cfg)
            res = run_episode(env, ctrl, spec.env_seed, keep_log=True, max_steps=spec.max_steps)
        finally:
            env.close()
        row = {**head, **episode_row(res), **_traces(res)}
    except Exception as exc:  # noqa: BLE001  (a crashed run is a result too; the campaign goes on)
        row = {
            **head, "outcome": "error", "cause": f"{type(exc).__name__}: {exc}"[:500],
            "docked": False, "trace_range_m": [], "trace_pos_err_m": [], "trace_att_err_deg": [],
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
    cluster = LocalCluster(
        n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
        silence_logs=logging.ERROR,
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


# ---------------------------------------------------------------------------------------------
# Storage
# ---------------------------------------------------------------------------------------------
def _write_part(parts: Path, row: dict[str, Any]) -> Path:
    import pandas as pd

    final = parts / f"run_{row['index']:06d}.parquet"
    return atomic_write(final, lambda tmp: pd.DataFrame([row]).to_parquet(tmp, index=False))


def _existing_parts(parts: Path) -> dict[int, Path]:
    """Part files by run index; temporary files of writes cut short (this process's or a dead
    process's) are removed, a live process's are left alone."""
    remove_stale_tmp(parts)
    out = {}
    if parts.is_dir():
        for p in parts.iterdir():
            m = _PART_RE.match(p.name)
            if m:
                out[int(m.group(1))] = p
    return out


def _read_part(path: Path, index: int) -> Any:
    """One part as a one-row table; ValueError when it is not the row of run ``index``."""
    import pandas as pd

    try:
        df = pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001  (pyarrow raises many types for a damaged file)
        raise ValueError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    if len(df) != 1 or not {"index", "outcome"} <= set(df) or int(df["index"].iloc[0]) != index:
        raise ValueError(f"expected one row of run {index}, got {len(df)} rows")
    return df


def _quarantine(path: Path) -> Path:
    """Move a damaged part into ``parts/quarantine/`` (never over an earlier one)."""
    qdir = path.parent / QUARANTINE_DIR
    qdir.mkdir(exist_ok=True)
    dest, k = qdir / path.name, 1
    while dest.exists():
        dest, k = qdir / f"{path.name}.{k}", k + 1
    os.replace(path, dest)
    fsync_dir(qdir)
    fsync_dir(path.parent)
    return dest


def _load_parts(parts: Path) -> dict[int, Any]:
    """The stored rows by run index; a part that cannot be read is quarantined (one warning line
    naming it) so that its run is done again."""
    rows = {}
    for i, p in sorted(_existing_parts(parts).items()):
        try:
            rows[i] = _read_part(p, i)
        except ValueError as exc:
            dest = _quarantine(p)
            log.warning("warning: %s is damaged (%s); moved to %s, run %d is done again",
                        p, exc, dest, i)
    return rows


def _concat(frames: Sequence[Any]) -> Any:
    import pandas as pd

    if not frames:
        return pd.DataFrame()
    df = pd.concat(frames, ignore_index=True)
    return df.sort_values("index", kind="stable").reset_index(drop=True)


def _discard(out: Path) -> None:
    """``--fresh``: delete the files a campaign writes (known names only) in ``out``."""
    parts = out / "parts"
    for p in _existing_parts(parts).values():
        p.unlink()
    qdir = parts / QUARANTINE_DIR
    if qdir.is_dir():
        for p in qdir.iterdir():
            if _QUARANTINED_RE.match(p.name):
                p.unlink()
    for name in (*_SUMMARY_FILES, "campaign.yaml"):
        (out / name).unlink(missing_ok=True)
    for name in PLOT_FILES:
        (out / "plots" / name).unlink(missing_ok=True)
    remove_stale_tmp(out)


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
    k = int(df["docked"].sum()) if n else 0
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
        "docked": k,
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
    }


def format_summary(summary: dict[str, Any], title: str | None = None) -> str:
    """The summary as a two-column text table (the same for campaigns and ``evaluate``)."""
    from agents.benchmarks.timing import format_table

    s = summary
    causes = ", ".join(f"{c} {v}" for c, v in sorted(s["causes"].items())) or "-"
    rows = [
        ("runs", s["runs"]),
        ("docked", s["docked"]),
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


# ---------------------------------------------------------------------------------------------
# The campaign
# ---------------------------------------------------------------------------------------------
@dataclass
class CampaignResult:
    """What :func:`run_campaign` produced.

    Attributes:
        out_dir: the campaign folder.
        table: one row per run (``pandas.DataFrame``), sorted by index.
        summary: :func:`summarize` of the table.
        ran: indices run in this call (the rest were resumed from disk).
        complete: every index has a row.
        failed_to_execute: runs lost to a dead worker (rerun the campaign to retry them).
        wall_time_s: time spent running.
        plots: PNG files written.
    """

    out_dir: Path
    table: Any
    summary: dict[str, Any]
    ran: list[int]
    complete: bool
    failed_to_execute: int = 0
    wall_time_s: float = 0.0
    plots: list[Path] = field(default_factory=list)

    def summary_table(self, title: str | None = None) -> str:
        return format_summary(self.summary, title)


def run_campaign(
    cfg: CampaignConfig,
    out_dir: str | Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    serial: bool = False,
    fresh: bool = False,
    retry_errors: bool = False,
    progress: bool = True,
    plots: bool = True,
    connect_timeout_s: float = 10.0,
    on_result: Callable[[dict[str, Any]], None] | None = None,
) -> CampaignResult:
    """Run (or resume) a campaign into ``out_dir``.

    The folder is claimed with a marker (:mod:`agents.outputs`) and locked while the campaign
    runs: a folder tridar-env did not create is refused unless empty, and a second process on the
    same folder is refused. Parts that cannot be read back are moved to ``parts/quarantine/``
    and their runs done again.

    Args:
        cfg: the campaign.
        out_dir: results folder: ``campaign.yaml``, ``parts/``, ``results.parquet``,
            ``summary.json``, ``summary.txt``, ``plots/*.png``.
        scheduler: Dask scheduler address; None for an embedded LocalCluster.
        workers: LocalCluster workers (default: one per core).
        serial: run in this process instead (debugging, the benchmark's baseline).
        fresh: discard results already in ``out_dir`` (the files a campaign writes, nothing else).
        retry_errors: rerun runs whose stored outcome is ``error``.
        progress: show a tqdm bar.
        plots: write the PNG plots.
        connect_timeout_s: scheduler connection timeout.
        on_result: called with each new row after its part file is written.

    Raises:
        ConfigError: ``out_dir`` holds results of a different campaign config.
        OutputFolderError (a ValueError): ``out_dir`` was not created by a tridar-env campaign
            and is not empty, or another process is writing it.
        ValueError: the scheduler cannot be reached.
    """
    validate_campaign(cfg)
    out = Path(out_dir)
    check_folder(out, KIND, destroy="--fresh" if fresh else None)
    with contextlib.ExitStack() as held:
        if is_marked(out):  # an earlier campaign's folder: hold it before reading it
            held.enter_context(lock_folder(out))
        if not fresh:
            _check_same_campaign(cfg, out)
        # Connect before touching the disk: a bad scheduler leaves nothing behind.
        client_cm = (
            contextlib.nullcontext(None) if serial
            else open_client(scheduler, workers, connect_timeout_s)
        )
        with client_cm as client:
            if not is_marked(out):
                claim_folder(out, KIND)
                held.enter_context(lock_folder(out))
            if fresh:
                _discard(out)
            rows, todo, ran, wall = _run_missing(
                cfg, out, client, retry_errors=retry_errors, progress=progress,
                on_result=on_result,
            )
        return _finish(cfg, out, rows, todo, ran, wall, plots)


def _check_same_campaign(cfg: CampaignConfig, out: Path) -> None:
    saved = out / "campaign.yaml"
    if not saved.is_file():
        return
    try:
        old = load_config(saved, model=CampaignConfig)
    except ConfigError as exc:
        raise ConfigError(
            f"{saved} cannot be read back ({exc.args[0].splitlines()[0]}); pass --fresh to "
            "discard the old results"
        ) from None
    if old.identity() != cfg.identity():
        diff = sorted(k for k, v in cfg.identity().items() if old.identity().get(k) != v)
        raise ConfigError(
            f"{out} holds results of a different campaign (fields differ: {', '.join(diff)}); "
            "pass --fresh to discard them or choose another output folder"
        )


def _run_missing(
    cfg: CampaignConfig,
    out: Path,
    client: Any,
    *,
    retry_errors: bool,
    progress: bool,
    on_result: Callable[[dict[str, Any]], None] | None,
) -> tuple[dict[int, Any], list[int], list[int], float]:
    """Run the indices without a readable part; returns (stored rows by index, the indices
    that were to run, those that ran, wall time)."""
    parts = out / "parts"
    parts.mkdir(exist_ok=True)
    atomic_write(out / "campaign.yaml", lambda p: save_config(cfg, p))
    rows = _load_parts(parts)
    if retry_errors:
        for i, df in list(rows.items()):
            if df["outcome"].iloc[0] == "error":
                (parts / f"run_{i:06d}.parquet").unlink()
                del rows[i]
    todo = [i for i in range(cfg.runs) if i not in rows]
    if todo:
        for name in _SUMMARY_FILES:
            (out / name).unlink(missing_ok=True)
    ran: list[int] = []
    docked = 0
    t0 = time.perf_counter()
    bar = None
    if progress and todo:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.runs, initial=cfg.runs - len(todo), desc=cfg.name, unit="run")
    try:
        results = contextlib.closing(iter_results(build_specs(cfg, todo), client))
        with results as new_rows:
            for row in new_rows:
                _write_part(parts, row)
                ran.append(int(row["index"]))
                if bar is not None:
                    docked += row["outcome"] == "docked"
                    bar.update(1)
                    bar.set_postfix(docked=f"{docked}/{len(ran)}", refresh=False)
                if on_result is not None:
                    on_result(row)
    finally:
        if bar is not None:
            bar.close()
    # The new rows as stored (the Parquet round trip), exactly as a later resume reads them.
    for i in ran:
        rows[i] = _read_part(parts / f"run_{i:06d}.parquet", i)
    return rows, todo, ran, time.perf_counter() - t0


def _finish(
    cfg: CampaignConfig,
    out: Path,
    rows: dict[int, Any],
    todo: list[int],
    ran: list[int],
    wall: float,
    plots: bool,
) -> CampaignResult:
    in_range = [rows[i] for i in sorted(rows) if i < cfg.runs]
    table = _concat(in_range)
    complete = len(in_range) == cfg.runs
    summary = summarize(table)
    result = CampaignResult(
        out_dir=out, table=table, summary=summary, ran=sorted(ran), complete=complete,
        failed_to_execute=len(todo) - len(ran), wall_time_s=wall,
    )
    if complete:
        atomic_write(out / "results.parquet", lambda p: table.to_parquet(p, index=False))
        atomic_write(
            out / "summary.json", lambda p: p.write_text(json.dumps(summary, indent=2) + "\n")
        )
        atomic_write(
            out / "summary.txt",
            lambda p: p.write_text(format_summary(summary, f"campaign {cfg.name}") + "\n"),
        )
        if plots:
            result.plots = plot_campaign(table, mission_config(cfg).env.envelope, out / "plots")
    return result
