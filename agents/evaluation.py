"""Evaluation of a saved policy: a campaign without dispersions, flown by ``sb3:<model>``.

Episode ``i`` is run ``i`` of such a campaign, so ``evaluate`` and a campaign with
``controller: sb3:<model>`` give the same rows and the same summary table.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agents.campaign_spec import CampaignConfig, build_specs, mission_config, validate_campaign
from agents.campaign_summary import summarize
from agents.policies import load_policy, model_file, training_config_of
from agents.runner import iter_results, open_client
from agents.training_config import CONFIG_FILE, bare_id

__all__ = ["evaluate"]


def evaluate(
    model: str | Path,
    *,
    env_id: str | None = None,
    perception: str = "tridar",
    episodes: int = 20,
    seed: int = 0,
    config: dict[str, Any] | None = None,
    max_steps: int | None = None,
    progress: bool = True,
    on_episode: Callable[[dict[str, Any]], None] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Fly a saved policy for ``episodes`` episodes (deterministic actions) and summarise.

    Episode ``i`` uses reset seed ``agents.campaign_spec.env_seed(seed, i)``: the same as run ``i``
    of a campaign with that seed and ``controller: sb3:<model>``, so both give the same rows.

    Args:
        model: ``model.zip`` or its run folder.
        env_id: default: the id the policy was trained on (from ``training.yaml``).
        perception: ``tridar`` (the intended test), ``truth+noise`` or ``truth``.
        episodes: number of episodes.
        seed: evaluation seed.
        config: mission-config overrides (default: those of the training run).
        max_steps: optional step cap per episode.
        progress: tqdm bar over episodes.
        on_episode: called with each row (in completion order when run in parallel).
        workers: run the episodes on a Dask LocalCluster with this many worker processes
            (None or 1: in this process); ``scheduler``: or on an existing Dask scheduler.

    Returns:
        ``(table, summary)``: a ``pandas.DataFrame`` (one row per episode, campaign columns) and
        :func:`agents.campaign_summary.summarize` of it.
    """
    import pandas as pd

    if episodes < 1:
        raise ValueError(f"episodes={episodes}; expected >= 1")
    p = model_file(model)
    train_cfg = training_config_of(p)
    env_id = env_id or (train_cfg.env_id if train_cfg else None)
    if env_id is None:
        raise ValueError(f"no env id given and no {CONFIG_FILE} beside {p}; pass --env-id")
    if config is None:
        config = dict(train_cfg.config) if train_cfg and bare_id(train_cfg.env_id) == bare_id(env_id) else {}
    camp = CampaignConfig(
        name="evaluate", env_id=env_id, perception=perception,  # type: ignore[arg-type]
        controller=f"sb3:{p.resolve()}", runs=episodes, seed=seed, max_steps=max_steps,
        config=config, mission=train_cfg.mission if train_cfg else None,
    )
    validate_campaign(camp, "evaluate")
    # Fail fast, with one line, on a bad file or a policy that does not fit the env.
    load_policy(p, cfg=mission_config(camp))
    rows = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=episodes, desc="evaluate", unit="ep")
    parallel = scheduler is not None or (workers is not None and workers > 1)
    try:
        with open_client(scheduler, workers) if parallel else contextlib.nullcontext() as client:
            for row in iter_results(build_specs(camp), client):
                if row["outcome"] == "error":
                    raise ValueError(f"episode {row['index']} failed: {row['cause']}")
                rows.append(row)
                if on_episode is not None:
                    on_episode(row)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if len(rows) != episodes:
        raise ValueError(f"{episodes - len(rows)} of {episodes} episodes did not complete (a worker died)")
    table = pd.DataFrame(rows).sort_values("index", kind="stable").reset_index(drop=True)
    return table, summarize(table)
