"""Output folders: a tool deletes or overwrites only what it created (issue 17)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from agents.cli import main
from agents.outputs import (
    LOCK_FILE,
    MARKER_FILE,
    OutputFolderError,
    atomic_write,
    check_folder,
    check_name,
    claim_folder,
    is_marked,
    lock_folder,
    read_marker,
    remove_stale_tmp,
)

CAMPAIGN = {
    "name": "tiny", "env_id": "TriDAR/FinalApproach-v0", "perception": "truth",
    "controller": "glideslope", "runs": 1, "seed": 1, "max_steps": 5,
    "config": {"env__initial__range_m": 5.0},
}
TRAINING = {
    "name": "tiny", "algo": "ppo", "perception": "truth", "total_timesteps": 64, "n_envs": 1,
    "vec_env": "dummy", "checkpoint_every_steps": None,
    "hyperparams": {"n_steps": 32, "batch_size": 32, "n_epochs": 1},
}


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def user_folder(path: Path) -> Path:
    """A folder holding somebody's files with the names the tools write."""
    (path / "checkpoints").mkdir(parents=True)
    (path / "parts").mkdir()
    for name in ("model.zip", "checkpoints/model_100_steps.zip", "parts/run_000000.parquet",
                 "results.parquet", "summary.json", "notes.txt"):
        (path / name).write_text(f"user's {name}")
    return path


def untouched(path: Path) -> bool:
    return (path / "notes.txt").read_text() == "user's notes.txt" and all(
        (path / n).read_text() == f"user's {n}"
        for n in ("model.zip", "checkpoints/model_100_steps.zip", "parts/run_000000.parquet",
                  "results.parquet", "summary.json")
    ) and not (path / MARKER_FILE).exists()


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# ---------------------------------------------------------------------------------------------
# The helper module
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["tiny", "ppo_final_approach", "run-2.v1", "A1"])
def test_plain_names_pass(name):
    assert check_name(name) == name


@pytest.mark.parametrize("name", ["../../x", "..", "/tmp/x", "", "a/b", "a\\b", ".hidden", "x y",
                                  "-rf", "a" * 101])
def test_other_names_are_refused_naming_field_and_value(name):
    with pytest.raises(OutputFolderError) as exc:
        check_name(name, "name")
    msg = str(exc.value)
    assert msg.startswith(f"name={name!r} is not a plain folder name") and "\n" not in msg
    assert "--out" in msg


def test_claim_marks_new_and_empty_folders_and_refuses_others(tmp_path):
    new = claim_folder(tmp_path / "a" / "b", "campaign")
    marker = read_marker(new)
    assert marker["kind"] == "campaign" and marker["pid"] == os.getpid() and marker["created"]
    assert claim_folder(new, "campaign") == new  # ours: reused
    empty = tmp_path / "empty"
    empty.mkdir()
    assert read_marker(claim_folder(empty, "train"))["kind"] == "train"
    with pytest.raises(OutputFolderError, match="is a tridar-env campaign folder; expected a tr"):
        claim_folder(new, "train")
    theirs = user_folder(tmp_path / "theirs")
    with pytest.raises(OutputFolderError, match="not empty and was not created by tridar-env"):
        claim_folder(theirs, "campaign")
    with pytest.raises(OutputFolderError, match="not created by tridar-env .*--fresh deletes only"):
        check_folder(theirs, "campaign", destroy="--fresh")
    with pytest.raises(OutputFolderError, match="already exists"):
        claim_folder(new, "campaign", new=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputFolderError, match="is not a folder"):
        claim_folder(tmp_path / "file", "campaign")
    assert untouched(theirs)


def test_atomic_write_fsyncs_file_and_folder(tmp_path, monkeypatch):
    synced: list[int] = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    atomic_write(tmp_path / "x.txt", lambda p: p.write_text("hello"))
    assert (tmp_path / "x.txt").read_text() == "hello" and len(synced) == 2
    assert [p.name for p in tmp_path.iterdir()] == ["x.txt"]

    def cut_short(p: Path) -> None:
        p.write_text("half")
        raise RuntimeError("cut")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.txt", cut_short)
    assert (tmp_path / "x.txt").read_text() == "hello" and len(list(tmp_path.iterdir())) == 1


LOCKER = """
import sys, time
from agents.outputs import lock_folder
with lock_folder(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(60)
"""


@pytest.fixture
def locked_by_another_process():
    """Hold ``folder/.lock`` from a second process until the test ends."""
    procs = []

    def hold(folder: Path) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-c", LOCKER, str(folder)], stdout=subprocess.PIPE,
                                text=True)
        procs.append(proc)
        assert proc.stdout.readline().strip() == "locked"
        return proc

    yield hold
    for proc in procs:
        proc.kill()
        proc.wait()


def test_lock_refuses_a_second_process(tmp_path, locked_by_another_process):
    proc = locked_by_another_process(tmp_path)
    busy = f"in use by another tridar-env process \\(pid {proc.pid}\\)"
    with pytest.raises(OutputFolderError, match=busy):
        with lock_folder(tmp_path):
            pass
    proc.kill()
    proc.wait()
    with lock_folder(tmp_path) as path:  # released with the process
        assert path.name == LOCK_FILE


def test_only_own_or_dead_processes_tmp_files_are_removed(tmp_path):
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        theirs = tmp_path / f".run_000001.parquet.{live.pid}.tmp"
        dead = tmp_path / f".run_000002.parquet.{dead_pid()}.tmp"
        mine = tmp_path / f".model.zip.{os.getpid()}.tmp.zip"
        other = tmp_path / "user.tmp"
        for p in (theirs, dead, mine, other):
            p.write_text("x")
        assert sorted(remove_stale_tmp(tmp_path)) == sorted([dead, mine])
        assert theirs.exists() and other.exists()
    finally:
        live.kill()
        live.wait()


# ---------------------------------------------------------------------------------------------
# campaign
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../x", "ABSOLUTE", "a/b", ""])
def test_campaign_name_must_be_plain(tmp_path, monkeypatch, capsys, name):
    # Default folder runs/campaigns/<name> from tmp/a/b/work: ../../x would land in tmp/a/b.
    work = tmp_path / "a" / "b" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    name = str(tmp_path / "abs") if name == "ABSOLUTE" else name
    path = write_yaml(tmp_path / "c.yaml", {**CAMPAIGN, "name": name})
    assert main(["campaign", str(path), "--serial", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"name={name!r} is not a plain folder name" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "c.yaml"]
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == ["work"]
    assert not list(work.iterdir())


def test_campaign_fresh_refuses_a_folder_it_did_not_create(tmp_path, capsys):
    theirs = user_folder(tmp_path / "theirs")
    path = write_yaml(tmp_path / "c.yaml", CAMPAIGN)
    assert main(["campaign", str(path), "--out", str(theirs), "--serial", "--fresh",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{theirs} was not created by tridar-env" in err
    # Without --fresh it would mix its files with the user's: refused too.
    assert main(["campaign", str(path), "--out", str(theirs), "--serial", "--no-progress"]) == 2
    assert "not empty and was not created by tridar-env" in capsys.readouterr().err
    assert untouched(theirs)


def test_campaign_fresh_deletes_only_what_a_campaign_writes(tmp_path):
    from agents.campaign import CampaignConfig, run_campaign

    out = tmp_path / "o"
    run_campaign(CampaignConfig(**CAMPAIGN), out, serial=True, progress=False, plots=False)
    assert read_marker(out)["kind"] == "campaign"
    (out / "notes.txt").write_text("mine")
    (out / "parts" / "my.parquet").write_text("mine")
    (out / "plots").mkdir()
    (out / "plots" / "mine.png").write_text("mine")
    other = CampaignConfig(**{**CAMPAIGN, "seed": 2})
    res = run_campaign(other, out, serial=True, progress=False, plots=False, fresh=True)
    assert res.ran == [0] and res.table["env_seed"].nunique() == 1
    for p in ("notes.txt", "parts/my.parquet", "plots/mine.png"):
        assert (out / p).read_text() == "mine"


def test_campaign_refuses_an_evaluate_or_train_folder(tmp_path):
    from agents.campaign import CampaignConfig, run_campaign

    claim_folder(tmp_path / "t", "train")
    with pytest.raises(OutputFolderError, match="is a tridar-env train folder"):
        run_campaign(CampaignConfig(**CAMPAIGN), tmp_path / "t", serial=True, progress=False,
                     fresh=True)


# ---------------------------------------------------------------------------------------------
# train
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../x", "ABSOLUTE"])
def test_train_name_must_be_plain(tmp_path, monkeypatch, capsys, name):
    work = tmp_path / "a" / "b" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    name = str(tmp_path / "abs") if name == "ABSOLUTE" else name
    path = write_yaml(tmp_path / "t.yaml", {**TRAINING, "name": name})
    assert main(["train", str(path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"name={name!r} is not a plain folder name" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "t.yaml"]
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == ["work"]
    assert not list(work.iterdir())


def test_train_force_refuses_a_folder_it_did_not_create(tmp_path, capsys):
    theirs = user_folder(tmp_path / "theirs")
    path = write_yaml(tmp_path / "t.yaml", TRAINING)
    assert main(["train", str(path), "--out", str(theirs), "--force", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{theirs} was not created by tridar-env" in err
    assert "--force" in err
    assert untouched(theirs)


# ---------------------------------------------------------------------------------------------
# evaluate, demo
# ---------------------------------------------------------------------------------------------
def test_evaluate_out_refuses_a_folder_it_did_not_create(tmp_path, capsys):
    theirs = user_folder(tmp_path / "theirs")
    # Refused before the policy is even looked at (nothing is flown for nothing).
    assert main(["evaluate", str(tmp_path / "model.zip"), "--out", str(theirs)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not empty and was not created by tridar-env" in err
    claim_folder(tmp_path / "camp", "campaign")
    assert main(["evaluate", str(tmp_path / "model.zip"), "--out", str(tmp_path / "camp")]) == 2
    assert "is a tridar-env campaign folder; expected a evaluate folder" in capsys.readouterr().err
    assert untouched(theirs)


def test_evaluate_write_results_only_in_its_own_folder(tmp_path):
    import pandas as pd

    from agents.commands.evaluate import write_results

    out = tmp_path / "ev"
    write_results(out, pd.DataFrame({"index": [0]}), {"runs": 1})
    write_results(out, pd.DataFrame({"index": [0, 1]}), {"runs": 2})  # ours: replaced
    assert json.loads((out / "summary.json").read_text())["runs"] == 2
    assert read_marker(out)["kind"] == "evaluate"


def test_demo_never_writes_over_an_existing_stamped_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(time, "strftime", lambda fmt, *a: "20000101-000000")
    old = tmp_path / "reports" / "demo-20000101-000000"
    old.mkdir(parents=True)
    (old / "summary.json").write_text("earlier report")
    assert main(["demo", "--perception", "truth", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{Path('reports/demo-20000101-000000')} already exists" in err
    assert (old / "summary.json").read_text() == "earlier report"


def test_demo_out_refuses_a_folder_it_did_not_create(tmp_path, capsys):
    theirs = user_folder(tmp_path / "theirs")
    assert main(["demo", "--perception", "truth", "--out", str(theirs), "--no-progress"]) == 2
    assert "not empty and was not created by tridar-env" in capsys.readouterr().err
    assert untouched(theirs)


def test_check_target_writes_a_new_marked_folder_beside_an_existing_one(tmp_path, capsys):
    from perception.shapes import save_generated

    stl = tmp_path / "flat.stl"
    port, axis = save_generated("flat_face", 11, stl)
    theirs = user_folder(tmp_path / "theirs")
    args = ["check-target", str(stl), "--port", *(f"{v:.6f}" for v in port),
            "--axis", *(f"{v:.6f}" for v in axis), "--no-campaign", "--out", str(theirs)]
    assert main(args) == 0
    capsys.readouterr()
    assert untouched(theirs)
    report = tmp_path / "theirs-2"
    assert read_marker(report)["kind"] == "check-target" and (report / "report.txt").is_file()


def test_benchmark_report_folders_never_take_a_users_folder(tmp_path: Path) -> None:
    from agents.benchmarks.integrity import new_folder
    from agents.benchmarks.pipeline import plot

    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    with pytest.raises(OutputFolderError, match="not created by tridar-env"):
        plot({"rec": {}, "scenario": None}, user)  # refused before anything is drawn
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    # The integrity bench and check-target: a new marked sibling, never the existing folder.
    out = new_folder(user, "bench-integrity")
    assert out != user and is_marked(out) and (user / "notes.txt").read_text() == "keep"
