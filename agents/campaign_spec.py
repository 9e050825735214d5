"""What a campaign is: its YAML model, its dispersions and the run specs they give.

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

:func:`build_specs` turns a campaign into :class:`RunSpec` values, which :mod:`agents.runner`
flies; :mod:`agents.campaign` runs them into a resumable folder.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agents.outputs import check_name
from perception.config import ConfigError, MissionConfig, config_path, load_config
from tridar_env.registration import bare_id

__all__ = [
    "CampaignConfig",
    "Dispersion",
    "RunSpec",
    "bare_id",
    "build_specs",
    "check_run_identity",
    "env_seed",
    "load_campaign",
    "mission_config",
    "run_seed_sequence",
    "sample_overrides",
    "validate_campaign",
]

_DIST_KEYS = ("uniform", "loguniform", "normal", "choice", "constant")
_DIST_EXTRA = {"clip", "weights"}


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
    perception: Literal["truth", "truth+noise", "tridar", "flash"] = "tridar"
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


def check_run_identity(name: str, env_id: str, fail: Callable[[str], None]) -> None:
    """The checks a campaign and a training run share: ``name`` is a plain folder name and
    ``env_id`` a registered id; ``fail(message)`` raises the caller's one-line error."""
    from tridar_env.registration import ENV_IDS

    try:
        check_name(name)
    except ValueError as exc:
        fail(str(exc))
    if bare_id(env_id) not in ENV_IDS:
        fail(f"env_id={env_id!r} is not registered; expected one of {', '.join(ENV_IDS)}")


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

    def fail(msg: str) -> None:
        raise ConfigError(f"campaign {source}: {msg}")

    check_run_identity(cfg.name, cfg.env_id, fail)
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

    path = cfg.mission or config_path(ENV_IDS[bare_id(cfg.env_id)])
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
