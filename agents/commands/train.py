"""``tridar-env train CONFIG``: train an SB3 policy (PPO or SAC) from a training YAML."""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.cli import command


@command("train", "train a stable-baselines3 policy (PPO/SAC) from a training YAML")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="training YAML (or a name in configs/training)")
    p.add_argument("--out", type=Path, default=None,
                   help="run folder (default runs/train/<name>): model.zip, vecnormalize.npz, "
                        "training.yaml, learning_curve.csv/.png, checkpoints/, tb/")
    p.add_argument("--timesteps", type=int, default=None, help="override total_timesteps")
    p.add_argument("--n-envs", type=int, default=None, help="override n_envs")
    p.add_argument("--seed", type=int, default=None, help="override the seed")
    p.add_argument("--perception", choices=["truth", "truth+noise", "tridar"], default=None,
                   help="override the perception mode used for training")
    p.add_argument("--force", action="store_true",
                   help="replace a model already in --out (only in a folder train created)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agents.training import load_training, train

    overrides = {
        k: v for k, v in {
            "total_timesteps": args.timesteps, "n_envs": args.n_envs, "seed": args.seed,
            "perception": args.perception,
        }.items() if v is not None
    }
    cfg = load_training(args.config, **overrides)
    out = args.out or Path("runs") / "train" / cfg.name
    res = train(cfg, out, progress=not args.no_progress, force=args.force)
    state = "interrupted after" if res.interrupted else "trained"
    print(f"{cfg.algo.upper()} {state} {res.timesteps} steps in {res.wall_time_s:.1f} s "
          f"({res.timesteps / max(res.wall_time_s, 1e-9):.0f} steps/s) on {cfg.n_envs} envs")
    print(f"policy: {res.model_path}; statistics: {res.stats_path}; "
          f"learning curve: {out / 'learning_curve.png'}; "
          f"TensorBoard: tensorboard --logdir {out / 'tb'}")
    best = out / "best_model.zip"
    target = best if cfg.validation is not None and best.is_file() else out
    print(f"next: tridar-env evaluate {target} --perception tridar --episodes 100")
    return 130 if res.interrupted else 0
