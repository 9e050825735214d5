"""Training throughput: SB3 steps/s of a training config on each vector env, same config otherwise.

Builds the run exactly as ``tridar-env train`` does (its vector env, ``VecNormalize``, the SB3
model with the config's hyperparameters, the outcome logger) and times ``model.learn`` over
``--steps`` environment steps, once per vector env per repeat (the order alternates between
repeats, so that a neighbour's load falls on both). Rollouts, PPO updates and normalisation are
all in the time; the behaviour-cloning warm start and checkpoints are not. The peer row is
``subproc`` (one process per environment, the path every run took before the batched adapter);
``batched`` is :class:`agents.vec_adapter.BatchedVecEnv`. Goal (issue 22): batched >= 3x subproc
on truth+noise with the same config and ``n_envs``.

    tridar-env bench train --config ppo_final_approach --steps 32768 --repeats 3
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from agents.benchmarks.timing import format_table

GOAL = 3.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        default="ppo_final_approach",
        help="training YAML (or a name in configs/training); its pretrain is skipped",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=32_768,
        help="environment steps per measurement (SB3 rounds up to whole rollouts)",
    )
    p.add_argument("--repeats", type=int, default=3, help="measurements per row (median, p90)")
    p.add_argument(
        "--n-envs",
        type=int,
        nargs="*",
        default=None,
        help="n_envs values (default: the config's); the ratio compares equal n_envs",
    )
    p.add_argument(
        "--vec-envs",
        nargs="*",
        default=["subproc", "batched"],
        choices=["subproc", "dummy", "batched"],
        help="vector envs to time (the first is the peer of the ratio)",
    )
    p.add_argument(
        "--perception",
        choices=["truth", "truth+noise"],
        default=None,
        help="override the config's perception",
    )


def _steps_per_s(cfg, steps: int) -> float:
    """Build the run of ``cfg`` and time ``learn(steps)``: environment steps per second."""
    import torch

    from agents.learning_curve import LearningCurve
    from agents.training import build_model, make_training_env, validate_training

    torch.set_num_threads(cfg.torch_threads)
    venv, _ = make_training_env(cfg, validate_training(cfg))
    try:
        _, model = build_model(cfg, venv)
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps, callback=LearningCurve(), progress_bar=False)
        wall = time.perf_counter() - t0
        return model.num_timesteps / wall
    finally:
        venv.close()


def run(args: argparse.Namespace) -> int:
    from agents.training import load_training

    if args.steps < 1 or args.repeats < 1:
        raise ValueError(f"--steps {args.steps} --repeats {args.repeats}; expected both >= 1")
    base = load_training(args.config)
    fixed = {"pretrain": None, "checkpoint_every_steps": None}
    if args.perception is not None:
        fixed["perception"] = args.perception
    rows = []
    for n_envs in args.n_envs or [base.n_envs]:
        cfgs = {
            kind: base.model_copy(update={**fixed, "vec_env": kind, "n_envs": n_envs})
            for kind in args.vec_envs
        }
        rates: dict[str, list[float]] = {kind: [] for kind in args.vec_envs}
        for r in range(args.repeats):
            for kind in args.vec_envs[:: 1 if r % 2 == 0 else -1]:
                rates[kind].append(_steps_per_s(cfgs[kind], args.steps))
        peer = float(np.median(rates[args.vec_envs[0]]))
        for kind in args.vec_envs:
            med = float(np.median(rates[kind]))
            rows.append(
                {
                    "config": base.name,
                    "perception": cfgs[kind].perception,
                    "vec_env": kind,
                    "n_envs": n_envs,
                    "steps": args.steps,
                    "steps_per_s_median": med,
                    # the slow tail: the 10th percentile of the rate is the 90th of the time per step
                    "steps_per_s_p90": float(np.percentile(rates[kind], 10)),
                    f"ratio_to_{args.vec_envs[0]}": med / peer,
                }
            )
    print(format_table(rows))
    print(f"goal: batched >= {GOAL:g}x subproc (same config, same n_envs)")
    return 0
