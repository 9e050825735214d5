"""The baseline table (``tridar-env evaluate --table SPEC``): scripted controllers and learned
policies on truth, truth plus noise and the full pipeline, one line per row and perception.

A spec YAML (model :class:`BaselineSpec`, ``configs/baselines.yaml``) lists rows::

    rows:
      - {env_id: TriDAR/FinalApproach-v0, policy: glideslope, perceptions: [truth, truth+noise, tridar]}
      - {env_id: TriDAR/FinalApproach-v0, policy: "sb3:runs/train/ppo_final_approach",
         perceptions: [truth, tridar], episodes: 100, seed: 0}

Each row and perception is flown with the campaign machinery, never a second episode loop: a
scripted controller as a campaign without dispersions (:func:`agents.campaign_spec.build_specs`,
:func:`agents.runner.iter_results`; the same rows as ``tridar-env campaign`` with that controller,
perception and seed and no ``config`` or ``dispersions``), an ``sb3:<path>`` policy through
:func:`agents.evaluation.evaluate`, so its line equals ``tridar-env evaluate PATH ...`` exactly.
Figures come from :func:`agents.campaign_summary.summarize` (its Wilson interval included); the
contact figures are those of the docked runs alone. Each line carries the one command that
reproduces it: ``tridar-env evaluate PATH --env-id ... --perception ...`` for a policy,
``tridar-env evaluate --table SPEC --only ROW --perception ...`` for a scripted controller. A
scripted episode that crashes counts as a failure and is noted under the table (as in a campaign);
a policy's line stops at one (as ``evaluate`` does).

A policy's training figures are what its run folder records: the steps trained (``num_timesteps``
of ``model.zip``) and the wall time of SB3's learning loop (the learning curve's, else from its
start time in ``model.zip`` to the last TensorBoard event at or before those steps); "-" when the
folder does not hold them.
"""

from __future__ import annotations

import contextlib
import json
import math
import shlex
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from agents.training_config import CURVE_FILE
from perception.config import load_config

__all__ = [
    "PERCEPTIONS",
    "BaselineRow",
    "BaselineSpec",
    "Line",
    "TrainingInfo",
    "format_markdown",
    "line_figures",
    "load_spec",
    "pipeline_gap",
    "reproduce_command",
    "rows_document",
    "run_table",
    "select",
    "training_info",
    "write_table",
]

Perception = Literal["truth", "truth+noise", "tridar", "flash"]
PERCEPTIONS: tuple[str, ...] = ("truth", "truth+noise", "tridar", "flash")
#: The perception whose score the gap column subtracts from the truth score.
PIPELINE = "tridar"


# ---------------------------------------------------------------------------------------------
# The spec
# ---------------------------------------------------------------------------------------------
class BaselineRow(BaseModel):
    """One row of the table: a policy on an id, evaluated on each of ``perceptions``.

    Attributes:
        env_id: a registered id (``TriDAR/FinalApproach-v0``, ...).
        policy: a scripted controller name (:data:`agents.controllers.CONTROLLERS`) or
            ``sb3:<path>`` (``model.zip`` or its run folder, relative to the working folder).
        perceptions: a non-empty subset of ``truth``, ``truth+noise``, ``tridar``, ``flash``.
        episodes: episodes per perception.
        seed: evaluation seed (episode ``i``: the campaign seed rule of run ``i``).
        max_steps: optional cap on steps per episode (outcome ``timeout``).
    """

    model_config = ConfigDict(extra="forbid")

    env_id: str
    policy: str
    perceptions: Annotated[list[Perception], Field(min_length=1)]
    episodes: Annotated[int, Field(ge=1, le=1_000_000)] = 100
    seed: Annotated[int, Field(ge=0)] = 0
    max_steps: Annotated[int, Field(ge=1)] | None = None

    @field_validator("env_id")
    @classmethod
    def _registered(cls, v: str) -> str:
        from tridar_env.registration import ENV_IDS, bare_id

        if bare_id(v) not in ENV_IDS:
            raise ValueError(f"one of {', '.join(ENV_IDS)}")
        return v

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, v: str) -> str:
        from agents.controllers import CONTROLLERS, controller_names

        if v in CONTROLLERS or (v.startswith("sb3:") and len(v) > 4):
            return v
        raise ValueError(f"one of {', '.join(controller_names())} or 'sb3:<path to model.zip>'")

    @field_validator("perceptions")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("each perception once")
        return v

    @property
    def is_sb3(self) -> bool:
        return self.policy.startswith("sb3:")


class BaselineSpec(BaseModel):
    """A baseline table: its rows, in the order the table shows them (``--only`` counts from 0)."""

    model_config = ConfigDict(extra="forbid")

    rows: Annotated[list[BaselineRow], Field(min_length=1)]


def load_spec(path: str | Path) -> BaselineSpec:
    """Read and check a spec YAML: fields (one line naming field, value and expectation), then
    every scripted row's mission for each of its perceptions and every policy file.

    Raises:
        ConfigError: a field, value or mission that does not validate.
        FileNotFoundError: an ``sb3:`` path without a model.
    """
    from agents.campaign_spec import validate_campaign
    from agents.policies import model_file

    spec = load_config(path, model=BaselineSpec)
    for i, row in enumerate(spec.rows):
        if row.is_sb3:
            model_file(row.policy[4:])
            continue
        for perception in row.perceptions:
            validate_campaign(_campaign(row, perception), f"{path} rows.{i} ({perception})")
    return spec


def _campaign(row: BaselineRow, perception: str) -> Any:
    """The campaign without dispersions that a scripted row flies on ``perception``."""
    from agents.campaign_spec import CampaignConfig

    return CampaignConfig(
        name="baseline", env_id=row.env_id, perception=perception,  # type: ignore[arg-type]
        controller=row.policy, runs=row.episodes, seed=row.seed, max_steps=row.max_steps,
    )


# ---------------------------------------------------------------------------------------------
# Figures of one line
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainingInfo:
    """What a policy's run folder records: steps trained and the learning loop's wall time [s]
    (None when not recorded)."""

    steps: int | None
    wall_time_s: float | None


@dataclass
class Line:
    """One line of the table: row ``row`` of the spec on ``perception``.

    Attributes:
        row: index in the spec; ``spec``: the row as evaluated (overrides applied).
        perception: the perception mode.
        table: one results row per episode (``pandas.DataFrame``, campaign columns).
        figures: :func:`line_figures` of ``table``.
        training: a policy's :class:`TrainingInfo` (None for a scripted controller).
        gap_pp: the row's truth minus pipeline success [percentage points] (None unless both
            were evaluated).
        command: the shell command that reproduces this line alone.
    """

    row: int
    spec: BaselineRow
    perception: str
    table: Any
    figures: dict[str, Any]
    training: TrainingInfo | None
    gap_pp: float | None
    command: str


def line_figures(table: Any) -> dict[str, Any]:
    """:func:`agents.campaign_summary.summarize` of ``table``, with the contact figures of its
    docked runs only (closing speed median, lateral offset p90) in place of all contacts'."""
    from agents.campaign_summary import summarize

    s = summarize(table)
    n = len(table)
    docked = table[table["docked"].astype(bool)] if n else table
    d = summarize(docked)
    s["contact_closing_speed_median_m_s"] = d["contact_closing_speed_median_m_s"]
    s["contact_lateral_offset_p90_m"] = d["contact_lateral_offset_p90_m"]
    return s


def pipeline_gap(truth_rate: float | None, pipeline_rate: float | None) -> float | None:
    """Truth minus pipeline success [percentage points]; None when either is missing or NaN."""
    if truth_rate is None or pipeline_rate is None:
        return None
    if not (math.isfinite(truth_rate) and math.isfinite(pipeline_rate)):
        return None
    return 100.0 * (truth_rate - pipeline_rate)


def training_info(model: str | Path) -> TrainingInfo:
    """Steps and learning-loop wall time of a policy, read from its run folder (no unpickling:
    the JSON ``data`` member of ``model.zip``, the learning curve and the TensorBoard event files).

    The steps are ``num_timesteps``; the wall time is the learning curve's (``learning_curve.csv``
    beside the model, as for ``model.zip`` and ``best_model.zip``: its last row at or before those
    steps), else it runs from
    ``start_time`` (when SB3's ``learn`` began) to the last TensorBoard event at or before those
    steps, in the event file that ``learn`` opened (the one created within a minute of
    ``start_time``).
    """
    from agents.policies import model_file

    p = model_file(model)
    try:
        with zipfile.ZipFile(p) as z:
            data = json.loads(z.read("data").decode())
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return TrainingInfo(None, None)
    steps = data.get("num_timesteps") if isinstance(data, dict) else None
    steps = int(steps) if isinstance(steps, int) and not isinstance(steps, bool) else None
    curve = p.parent / CURVE_FILE
    if steps is not None and curve.is_file():
        from agents.learning_curve import read_learning_curve

        try:
            c = read_learning_curve(curve)
        except (OSError, ValueError):
            c = None
        if c is not None:
            upto = c["timesteps"] <= steps
            if upto.any():
                return TrainingInfo(steps, float(c["wall_s"][upto][-1]))
    start = data.get("start_time") if isinstance(data, dict) else None
    if steps is None or not isinstance(start, (int, float)) or isinstance(start, bool):
        return TrainingInfo(steps, None)
    start_s = float(start) / 1e9  # time.time_ns()
    for folder in (p.parent, p.parent.parent):
        for events in sorted((folder / "tb").glob("*/events.out.tfevents.*")):
            wall = _learning_wall_time(events, start_s, steps)
            if wall is not None:
                return TrainingInfo(steps, wall)
    return TrainingInfo(steps, None)


def _learning_wall_time(events: Path, start_s: float, steps: int) -> float | None:
    """Seconds from ``start_s`` to the last event of ``events`` at or before ``steps``, when
    the file was opened by the ``learn`` that started at ``start_s``; else None."""
    try:
        from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    except ImportError:
        return None
    first = last = None
    try:
        for ev in EventFileLoader(str(events)).Load():
            if first is None:
                first = ev.wall_time
                if abs(first - start_s) > 60.0:
                    return None
            if ev.step <= steps and ev.summary.value:
                last = ev.wall_time
    except Exception:  # noqa: BLE001  (a damaged log is "not recorded", not a failed table)
        return None
    return None if last is None else max(last - start_s, 0.0)


def reproduce_command(
    row: BaselineRow, index: int, perception: str, spec_path: str | Path
) -> str:
    """The one command that flies this line alone (shell-quoted)."""
    if row.is_sb3:
        cmd = ["tridar-env", "evaluate", row.policy[4:], "--env-id", row.env_id]
    else:
        cmd = ["tridar-env", "evaluate", "--table", str(spec_path), "--only", str(index)]
    cmd += ["--perception", perception, "--episodes", str(row.episodes), "--seed", str(row.seed)]
    if row.max_steps is not None:
        cmd += ["--max-steps", str(row.max_steps)]
    return shlex.join(cmd)


# ---------------------------------------------------------------------------------------------
# Running the table
# ---------------------------------------------------------------------------------------------
def select(
    spec: BaselineSpec, only: Sequence[int] | None = None, perception: str | None = None
) -> list[tuple[int, str]]:
    """The ``(row index, perception)`` lines to fly, in table order.

    Raises:
        ValueError: an index outside the spec, or nothing left to evaluate.
    """
    n = len(spec.rows)
    for i in only or ():
        if not 0 <= i < n:
            raise ValueError(f"--only {i}: the spec has rows 0..{n - 1}; expected one of them")
    lines = [(i, p) for i, row in enumerate(spec.rows) if not only or i in only
             for p in row.perceptions if perception is None or p == perception]
    if not lines:
        raise ValueError(f"no row of the spec{' selected by --only' if only else ''} lists "
                         f"perception {perception!r}; expected one of the rows' perceptions")
    return lines


def run_table(
    spec: BaselineSpec,
    spec_path: str | Path,
    *,
    only: Sequence[int] | None = None,
    perception: str | None = None,
    episodes: int | None = None,
    seed: int | None = None,
    max_steps: int | None = None,
    progress: bool = True,
    workers: int | None = None,
    scheduler: str | None = None,
) -> list[Line]:
    """Fly the selected lines of ``spec`` and return them with their figures.

    Args:
        spec: the table; ``spec_path``: its file (named in the reproducing commands).
        only: row indices to fly (default: all); ``perception``: only this perception.
        episodes, seed, max_steps: replace every selected row's own.
        progress: one tqdm bar over all episodes.
        workers, scheduler: run the episodes on Dask (as ``evaluate --workers/--scheduler``).

    Raises:
        ValueError: a bad selection, or episodes that did not complete.
    """
    update = {k: v for k, v in {"episodes": episodes, "seed": seed, "max_steps": max_steps}.items()
              if v is not None}
    rows = {i: BaselineRow.model_validate({**r.model_dump(), **update}) for i, r in enumerate(spec.rows)}
    todo = select(spec, only, perception)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(rows[i].episodes for i, _ in todo), desc="baselines", unit="ep")
    tick: Callable[[dict[str, Any]], None] = (lambda _row: bar.update(1)) if bar else (lambda _row: None)
    lines: list[Line] = []
    try:
        for i, p in todo:
            row = rows[i]
            if bar is not None:
                bar.set_postfix_str(f"row {i} {row.policy} {p}", refresh=False)
            table = _fly(row, p, tick, workers, scheduler)
            lines.append(Line(
                row=i, spec=row, perception=p, table=table, figures=line_figures(table),
                training=training_info(row.policy[4:]) if row.is_sb3 else None, gap_pp=None,
                command=reproduce_command(row, i, p, spec_path),
            ))
    finally:
        if bar is not None:
            bar.close()
    for line in lines:
        rates = {ln.perception: ln.figures["success_rate"] for ln in lines if ln.row == line.row}
        line.gap_pp = pipeline_gap(rates.get("truth"), rates.get(PIPELINE))
    return lines


def _fly(
    row: BaselineRow,
    perception: str,
    tick: Callable[[dict[str, Any]], None],
    workers: int | None,
    scheduler: str | None,
) -> Any:
    """The results table of one line (one row per episode)."""
    import pandas as pd

    from agents.campaign_spec import build_specs
    from agents.evaluation import evaluate
    from agents.runner import iter_results, open_client

    if row.is_sb3:
        table, _ = evaluate(
            row.policy[4:], env_id=row.env_id, perception=perception, episodes=row.episodes,
            seed=row.seed, max_steps=row.max_steps, progress=False, on_episode=tick,
            workers=workers, scheduler=scheduler,
        )
        return table
    camp = _campaign(row, perception)
    parallel = scheduler is not None or (workers is not None and workers > 1)
    got = []
    with open_client(scheduler, workers) if parallel else contextlib.nullcontext() as client:
        for r in iter_results(build_specs(camp), client):
            got.append(r)
            tick(r)
    if len(got) != row.episodes:
        raise ValueError(f"{row.env_id} {row.policy} on {perception}: {row.episodes - len(got)} of "
                         f"{row.episodes} episodes did not complete (a worker died)")
    return pd.DataFrame(got).sort_values("index", kind="stable").reset_index(drop=True)


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------
_HEADER = ("#", "env id", "policy", "perception", "episodes", "success %", "Wilson 95 %",
           "delta-v median [m/s]", "closing speed median [m/s]", "lateral offset p90 [m]",
           "training wall time", "training steps", "truth - pipeline gap [pp]", "reproduce")


def _num(x: Any, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def _duration(s: float | None) -> str:
    if s is None:
        return "-"
    if s < 120:
        return f"{s:.0f} s"
    return f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h"


def _cells(line: Line) -> list[str]:
    f, t = line.figures, line.training
    return [
        str(line.row), line.spec.env_id, f"`{line.spec.policy}`", line.perception, str(f["runs"]),
        _num(100 * f["success_rate"], ".1f"),
        f"[{_num(100 * f['wilson95_low'], '.1f')}, {_num(100 * f['wilson95_high'], '.1f')}]",
        _num(f["delta_v_median_m_s"], ".3g"), _num(f["contact_closing_speed_median_m_s"], ".3g"),
        _num(f["contact_lateral_offset_p90_m"], ".3g"),
        _duration(t.wall_time_s if t else None), _num(t.steps if t else None, ","),
        _num(line.gap_pp, "+.1f"), f"`{line.command}`",
    ]


def format_markdown(lines: Sequence[Line]) -> str:
    """The table in Markdown, with a note per line whose episodes crashed."""
    out = ["| " + " | ".join(_HEADER) + " |", "|" + "|".join("---" for _ in _HEADER) + "|"]
    out += ["| " + " | ".join(c.replace("|", "\\|") for c in _cells(ln)) + " |" for ln in lines]
    out.append("")
    out.append("success: docked (FlyAround-v0: fly-around completed); contact figures over docked "
               "runs; delta-v over all runs; gap: truth minus tridar success, percentage points.")
    for ln in lines:
        if ln.figures["errors"]:
            first = ln.table.loc[ln.table["outcome"] == "error", "cause"].iloc[0]
            out.append(f"row {ln.row} on {ln.perception}: {ln.figures['errors']} episodes crashed "
                       f"(counted as failures), e.g. {first}")
    return "\n".join(out)


def rows_document(lines: Sequence[Line], spec: BaselineSpec, spec_path: str | Path) -> dict[str, Any]:
    """What ``rows.json`` holds: the spec as given and, per line, its settings and figures."""
    keep = ("runs", "docked", "succeeded", "success_rate", "wilson95_low", "wilson95_high",
            "errors", "causes", "delta_v_median_m_s", "contact_closing_speed_median_m_s",
            "contact_lateral_offset_p90_m")
    from agents.outputs import json_safe

    return json_safe({
        "spec_path": str(spec_path),
        "spec": spec.model_dump(mode="json"),
        "lines": [{
            "row": ln.row, **ln.spec.model_dump(mode="json", exclude={"perceptions"}),
            "perception": ln.perception, **{k: ln.figures[k] for k in keep},
            "training_steps": ln.training.steps if ln.training else None,
            "training_wall_time_s": ln.training.wall_time_s if ln.training else None,
            "truth_pipeline_gap_pp": ln.gap_pp, "command": ln.command,
        } for ln in lines],
    })


def write_table(out: Path, kind: str, markdown: str, document: dict[str, Any]) -> None:
    """``table.md`` and ``rows.json`` in ``out`` (a folder of ``kind`` or a new or empty one),
    each written atomically under the folder's lock."""
    from agents.outputs import atomic_write, claim_folder, lock_folder

    claim_folder(out, kind)
    with lock_folder(out):
        atomic_write(out / "table.md", lambda p: p.write_text(markdown + "\n"))
        atomic_write(out / "rows.json", lambda p: p.write_text(json.dumps(document, indent=2) + "\n"))

