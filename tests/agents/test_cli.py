"""The command line under careless and hostile input (issue 17): one line, a meaningful exit code.

Bad input exits 2, Ctrl-C 130, SIGTERM 143 (worker pools shut down, no leaked semaphores),
anything else 1 with an "internal error" line; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import io
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time
import warnings
import zipfile
from pathlib import Path

import pytest
import yaml

from agents.cli import COMMANDS, build_parser, main
from perception.config import ConfigError


@pytest.fixture
def boom(monkeypatch: pytest.MonkeyPatch):
    """Register a subcommand ``boom`` whose handler raises the given exception."""

    def use(exc: BaseException) -> None:
        def handler(args):
            raise exc

        monkeypatch.setitem(COMMANDS, "boom", ("raise an exception",
                                               lambda p: p.set_defaults(handler=handler)))

    return use


TORCH_REFUSAL = (
    "Weights only load failed. In PyTorch 2.6, we changed the default value of the `weights_only` "
    "argument in `torch.load` from `False` to `True`. Re-running `torch.load` with `weights_only` "
    "set to `False` will likely succeed, but it can result in arbitrary code execution.\n\n\n"
    "Trying to load unsupported GLOBAL posix.system whose module posix is blocked.\n\n"
    "Check the documentation of torch.load to learn more."
)


@pytest.mark.parametrize(
    "exc, words",
    [
        (pickle.UnpicklingError(TORCH_REFUSAL), ["refused to unpickle", "GLOBAL posix.system"]),
        (zipfile.BadZipFile("File is not a zip file"), ["not a valid zip file"]),
        (PermissionError(13, "Permission denied", "/runs/model.zip"),
         ["Permission denied", "/runs/model.zip"]),
        (IsADirectoryError(21, "Is a directory", "/runs"), ["Is a directory", "/runs"]),
        (UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"),
         ["expected encoding", "0xff"]),
        (MemoryError("Unable to allocate 7.28 TiB for an array"), ["out of memory", "7.28 TiB"]),
        (ConfigError("invalid configuration in c.yaml:\n  runs: got 0; expected >= 1\n"
                     "  colour: unknown key (value 'red'); check the spelling"),
         ["c.yaml: runs: got 0", " | colour: unknown key"]),
        (ValueError("first\nsecond"), ["first | second"]),
        (FileNotFoundError("policy file x.zip does not exist"), ["x.zip does not exist"]),
        (EOFError("Ran out of input"), ["Ran out of input"]),
    ],
)
def test_bad_input_is_one_line_and_exit_2(boom, capsys, exc, words) -> None:
    boom(exc)
    assert main(["boom"]) == 2
    out, err = capsys.readouterr()
    assert err.startswith("tridar-env boom: error: ") and err.count("\n") == 1, err
    for w in words:
        assert w in err, err
    assert "Traceback" not in err and "weights_only" not in err and not out


def test_unexpected_errors_are_one_internal_error_line_and_exit_1(boom, capsys) -> None:
    boom(RuntimeError("tensor shape mismatch\nin layer 3"))
    assert main(["boom"]) == 1
    err = capsys.readouterr().err
    assert err == ("tridar-env boom: internal error: RuntimeError: tensor shape mismatch | in "
                   "layer 3 (rerun with --debug for the traceback)\n")
    boom(KeyError("x"))
    assert main(["boom"]) == 1
    assert "internal error: KeyError: 'x'" in capsys.readouterr().err


def test_ctrl_c_is_one_interrupted_line_and_exit_130(boom, capsys) -> None:
    boom(KeyboardInterrupt())
    assert main(["boom"]) == 130
    assert capsys.readouterr().err == "tridar-env boom: interrupted\n"


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_the_traceback(boom, capsys, where: str) -> None:
    argv = ["--debug", "boom"] if where == "before" else ["boom", "--debug"]
    boom(RuntimeError("deep down"))
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("Traceback") and "RuntimeError: deep down" in err and "rerun" not in err
    boom(pickle.UnpicklingError("refused"))
    assert main(argv) == 2  # the exit code does not change with --debug
    assert "Traceback" in capsys.readouterr().err


def test_a_warning_prints_as_one_line_naming_the_command(monkeypatch) -> None:
    """Printed warnings are one line (no source path and code line); recorded ones still reach
    whoever records them; --debug keeps Python's format; the format is restored afterwards."""
    seen: list[str] = []

    def handler(args):
        seen.append(warnings.formatwarning(UserWarning("mesh m.stl: 1310720 faces\nsimplified"),
                                           UserWarning, "/src/agents/commands/scan.py", 93))
        warnings.warn("still recorded", UserWarning, stacklevel=1)
        return 0

    monkeypatch.setitem(COMMANDS, "warner", ("warn", lambda p: p.set_defaults(handler=handler)))
    before = warnings.formatwarning
    with pytest.warns(UserWarning, match="still recorded"):
        assert main(["warner"]) == 0
    assert seen[-1] == "tridar-env warner: warning: mesh m.stl: 1310720 faces | simplified\n"
    assert warnings.formatwarning is before
    with pytest.warns(UserWarning):
        assert main(["warner", "--debug"]) == 0
    assert seen[-1].startswith("/src/agents/commands/scan.py:93: UserWarning: mesh m.stl")


def test_debug_is_accepted_after_nested_subcommands() -> None:
    parser = build_parser()
    assert parser.parse_args(["bench", "soak", "--debug"]).debug is True
    assert parser.parse_args(["--debug", "bench", "soak"]).debug is True
    assert parser.parse_args(["bench", "soak"]).debug is False


def test_a_blocked_malicious_policy_is_one_line(tmp_path: Path, capsys) -> None:
    """A real SB3 archive whose ``policy.pth`` pickles ``os.system``: refused, not run."""
    torch = pytest.importorskip("torch")
    sb3 = pytest.importorskip("stable_baselines3")
    import gymnasium as gym

    import tridar_env  # noqa: F401  (registers the ids)

    env = gym.make("TriDAR/FinalApproach-v0", perception="truth")
    good = tmp_path / "good.zip"
    sb3.PPO("MlpPolicy", env, n_steps=64, batch_size=64, policy_kwargs={"net_arch": [8]},
            device="cpu").save(good)
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    buf = io.BytesIO()
    torch.save({"weights": Payload()}, buf)
    evil = tmp_path / "model.zip"
    with zipfile.ZipFile(good) as zin, zipfile.ZipFile(evil, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info.filename,
                          buf.getvalue() if info.filename == "policy.pth" else zin.read(info))
    code = main(["evaluate", str(evil), "--env-id", "TriDAR/FinalApproach-v0", "--perception",
                 "truth", "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "posix.system" in err or "pickle" in err.lower()
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------
# Signals, in a child process
# ---------------------------------------------------------------------------------------------
# A subcommand that starts a pool of spawned worker processes (their semaphores are tracked by
# multiprocessing's resource tracker, which warns about any not released) and waits.
POOL_CLI = textwrap.dedent("""
    import multiprocessing as mp, sys, time
    from agents.cli import command, main

    @command("pool", "start a worker pool and wait")
    def add(p):
        def handler(args):
            with mp.get_context("spawn").Pool(2) as pool:
                pool.map(abs, [1, 2])
                print("ready", flush=True)
                time.sleep(60)
            return 0
        p.set_defaults(handler=handler)

    sys.exit(main(["pool"]))
""")


def _child(code: str, sig: int, ready: str | None = None, wait_for=None) -> subprocess.CompletedProcess:
    # A child started from a non-interactive shell may inherit SIGINT ignored; give it Ctrl-C's
    # disposition in a terminal.
    code = f"import signal; signal.signal(signal.SIGINT, signal.default_int_handler)\n{code}"
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    if ready is not None:
        assert proc.stdout.readline().strip() == ready
    if wait_for is not None:
        deadline = time.time() + 120
        while time.time() < deadline and not wait_for() and proc.poll() is None:
            time.sleep(0.1)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.parametrize(
    "sig, code, line",
    [(signal.SIGTERM, 143, "tridar-env pool: terminated (SIGTERM)"),
     (signal.SIGINT, 130, "tridar-env pool: interrupted")],
)
def test_signals_shut_the_pool_down_with_one_line(sig: int, code: int, line: str) -> None:
    res = _child(POOL_CLI, sig, ready="ready")
    assert res.returncode == code, res.stderr
    assert res.stderr == line + "\n", res.stderr  # no traceback, no leaked-semaphore warning


@pytest.mark.slow
def test_sigterm_in_a_campaign_closes_the_cluster(tmp_path: Path) -> None:
    """The tester's case: SIGTERM to a campaign on a LocalCluster left leaked semaphores."""
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({
        "name": "soak", "env_id": "TriDAR/FinalApproach-v0", "perception": "truth+noise",
        "controller": "glideslope", "runs": 12, "seed": 5, "max_steps": 3000,
        "config": {"env__initial__range_dispersion_m": 0.0},
        "dispersions": {"env__initial__range_m": {"uniform": [25.0, 30.0]}},
    }))
    out = tmp_path / "o"
    argv = ["campaign", str(path), "--out", str(out), "--workers", "2", "--no-progress",
            "--no-plots"]
    code = f"import sys; from agents.cli import main; sys.exit(main({argv!r}))"
    res = _child(code, signal.SIGTERM,
                 wait_for=lambda: len(list((out / "parts").glob("run_*.parquet"))) >= 1)
    assert res.returncode == 143, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines[-1] == "tridar-env campaign: terminated (SIGTERM)", res.stderr
    assert "Traceback" not in res.stderr and "leaked" not in res.stderr, res.stderr


def test_envs_lists_every_id_on_one_line(capsys) -> None:
    import json as _json

    from tridar_env.registration import ENV_IDS

    assert main(["envs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    for env_id, mission in ENV_IDS.items():
        (line,) = [ln for ln in lines if ln.startswith(env_id + " ")]
        assert mission in line
    assert main(["envs", "--json"]) == 0
    rows = _json.loads(capsys.readouterr().out)
    far = {r["id"]: r for r in rows}["TriDAR/FarRendezvous-v0"]
    assert far["steps_lengthen"] and far["start_range_m"] >= 4000.0
    assert {r["id"]: r for r in rows}["TriDAR/FlyAround-v0"]["task"] == "fly_around"
