"""Monte Carlo campaigns: N closed-loop runs over dispersions, executed with Dask, resumable.

A campaign YAML (model :class:`~agents.campaign_spec.CampaignConfig`; the dispersion forms and the
per-run seeds are described in :mod:`agents.campaign_spec`) becomes run specs, which
:mod:`agents.runner` flies on an embedded ``LocalCluster`` (the default), an existing scheduler
(``scheduler="tcp://host:port"``) or in this process; :mod:`agents.campaign_summary` summarises and
plots the rows. This module runs a campaign into its folder.

Storage: the client writes one Parquet part file per finished run (``parts/run_000042.parquet``,
written to a temporary name, fsynced and renamed), so an interrupted campaign resumes from what
exists and runs only the missing indices (a part that cannot be read back is moved to
``parts/quarantine/`` and its run done again); the final ``results.parquet`` is the union, one row
per run. The resolved campaign config is saved as ``campaign.yaml`` beside the results, and a
resume refuses to mix results of a different config. The folder carries the marker of
:mod:`agents.outputs` and is locked while a campaign writes it.

The names of the campaign's other modules are importable from here too (``from agents.campaign
import load_campaign, summarize, ...``).

Example:
    >>> from agents.campaign import load_campaign, run_campaign
    >>> cfg = load_campaign("configs/campaigns/final_approach_truth.yaml", runs=4)
    >>> res = run_campaign(cfg, "runs/campaign_demo")        # doctest: +SKIP
    >>> print(res.summary_table())                            # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.campaign_spec import (
    CampaignConfig,
    Dispersion,
    RunSpec,
    build_specs,
    env_seed,
    load_campaign,
    mission_config,
    run_seed_sequence,
    sample_overrides,
    validate_campaign,
)
from agents.campaign_summary import PLOT_FILES, format_summary, plot_campaign, summarize
from agents.outputs import (
    atomic_write,
    check_folder,
    claim_folder,
    fsync_dir,
    is_marked,
    lock_folder,
    remove_stale_tmp,
)
from agents.runner import episode_row, iter_results, make_env, open_client, run_one
from perception.config import ConfigError, load_config, save_config

__all__ = [
    "CampaignConfig",
    "CampaignResult",
    "Dispersion",
    "RunSpec",
    "build_specs",
    "env_seed",
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
    "sample_overrides",
    "summarize",
    "validate_campaign",
]

log = logging.getLogger(__name__)

_PART_RE = re.compile(r"^run_(\d{6,})\.parquet$")
_QUARANTINED_RE = re.compile(r"^run_\d{6,}\.parquet(\.\d+)?$")
#: Marker kind of a campaign folder (:mod:`agents.outputs`).
KIND = "campaign"
#: Damaged parts are moved here (inside ``parts/``) on resume.
QUARANTINE_DIR = "quarantine"
_SUMMARY_FILES = ("results.parquet", "summary.json", "summary.txt")


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
                    docked += bool(row.get("success", row["outcome"] == "docked"))
                    bar.update(1)
                    bar.set_postfix(succeeded=f"{docked}/{len(ran)}", refresh=False)
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
