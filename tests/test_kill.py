"""Issue 11: concurrent commands, killed parents, and resume after kill -9 at random instants.

Real `anfekf run` processes (each in its own session, so that its workers can be found by
process group) are paused, killed or raced against each other:

- two commands into one folder: one result, equal to a single run's, and a clear message from
  the other (the folder's lock);
- after kill -9 of the parent alone, no worker process survives 10 s and the parent's output pipe
  reaches its end (`anfekf run ... | tee log` ends); the lock is not left stale;
- kill -9 (or SIGTERM) at random instants over a whole batch, then the same command again: the
  result is always equal to an uninterrupted run's.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import MANIFEST_FILE, RUNS_DIR, STEPS_FILE, folder_lock, read_json

from .conftest import live_group_members, small_scenario, write_scenario

pytestmark = pytest.mark.slow
COMMAND = [sys.executable, "-c", "from anfekf_bench.cli import main; main()"]
WORKERS_GONE_S = 10.0


def cli(*args) -> object:
    return CliRunner().invoke(app, [str(a) for a in args])


def start(path: Path, out: Path, *flags: str) -> subprocess.Popen:
    """`anfekf run` in a new session: its process group holds it and its workers."""
    return subprocess.Popen(
        [*COMMAND, "run", str(path), "--out", str(out), *flags],
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def wait_until_gone(pgid: int, within: float = WORKERS_GONE_S) -> float:
    """Seconds until the group is empty; fails if it is not within `within` seconds."""
    started = time.monotonic()
    while live_group_members(pgid):
        assert time.monotonic() - started < within, f"workers alive after {within:g} s"
        time.sleep(0.05)
    return time.monotonic() - started


def wait_for_saved_run(proc: subprocess.Popen, target: Path, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not list((target / RUNS_DIR).glob("run-*.npz")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, f"no run saved within {timeout:g} s"
        time.sleep(0.02)


def steps_of(target: Path) -> pd.DataFrame:
    return pd.read_parquet(target / STEPS_FILE)


def kill_group(proc: subprocess.Popen) -> None:
    if proc.poll() is None or live_group_members(proc.pid):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.communicate()


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> tuple[Path, pd.DataFrame]:
    """The small world, 6 runs, and its uninterrupted steps (in process, one job)."""
    root = tmp_path_factory.mktemp("kill")
    path = write_scenario(root / "small.yaml", small_scenario(runs=6, jobs=2, record_every=8))
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), root / "reference")
    return path, steps_of(target)


# --- Two commands, one folder -------------------------------------------------------------------


def test_two_commands_into_one_folder_give_one_result_and_a_clear_message(scenario, tmp_path):
    path, reference = scenario
    out = tmp_path / "out"
    target = out / "small"
    first = start(path, out, "--jobs", "1")
    try:
        wait_for_saved_run(first, target)
        os.killpg(first.pid, signal.SIGSTOP)  # paused while it holds the folder
        try:
            saved = sorted((target / RUNS_DIR).iterdir())
            for flags in ([], ["--force"], ["--force", "--seed", "99"], ["--jobs", "2"]):
                other = cli("run", path, "--out", out, *flags)
                assert other.exit_code == 2, (flags, other.output)
                assert other.stderr.splitlines() == [
                    f"error: small: {target}: another anfekf command is writing this folder"
                    f" (pid {first.pid}); wait for it to finish, or use another --out"
                ], flags
                assert sorted((target / RUNS_DIR).iterdir()) == saved, "the other touched nothing"
        finally:
            os.killpg(first.pid, signal.SIGCONT)
        _, stderr = first.communicate(timeout=300)
        assert first.returncode == 0, stderr
    finally:
        kill_group(first)
    pd.testing.assert_frame_equal(steps_of(target), reference, check_exact=True)
    manifest = read_json(target / MANIFEST_FILE)
    assert manifest["seed"] == 7 and manifest["resumed_runs"] == []


# --- kill -9 of the parent alone ----------------------------------------------------------------


def test_workers_end_when_the_parent_is_killed(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("ANFEKF_WORKER_START_S", "0")  # workers, whatever the runs cost
    doc = small_scenario(name="many", runs=40, jobs=2, record_every=8)
    path = write_scenario(tmp_path / "many.yaml", doc)
    out = tmp_path / "out"
    target = out / "many"
    proc = start(path, out)
    try:
        wait_for_saved_run(proc, target)
        deadline = time.monotonic() + 120  # the first two runs run in the command itself
        while len(live_group_members(proc.pid)) < 3:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the command and its two workers"
            time.sleep(0.05)
        drained = threading.Event()

        def drain() -> None:  # like `| tee`: reads until every holder of the pipe closed it
            proc.stdout.read()
            proc.stderr.read()
            drained.set()

        threading.Thread(target=drain, daemon=True).start()
        os.kill(proc.pid, signal.SIGKILL)  # the parent only: the workers must go by themselves
        took = wait_until_gone(proc.pid)
        assert drained.wait(WORKERS_GONE_S - took + 1), "the output pipe is still held open"
    finally:
        kill_group(proc)
    with folder_lock(target):  # the kernel released the dead command's lock: not stale
        pass
    assert not (target / MANIFEST_FILE).exists()


# --- kill -9 at random instants, then resume ----------------------------------------------------


def wait_for_batch_start(proc: subprocess.Popen) -> bool:
    """Read the command's output up to its first line (`small: new results`, printed when the
    batch starts, after validation); False if it ended first."""
    line = proc.stdout.readline()
    return b": new results" in line or b": resuming" in line


@pytest.fixture(scope="module")
def batch_seconds(scenario, tmp_path_factory) -> float:
    """How long one uninterrupted batch takes from its start to the end of the command (one job:
    the runs, their saving and the final writes happen in the command itself), whose result must
    equal the in-process reference: the span over which the trials pick their instants."""
    path, reference = scenario
    out = tmp_path_factory.mktemp("whole") / "out"
    proc = start(path, out, "--jobs", "1")
    assert wait_for_batch_start(proc), proc.communicate()
    started = time.monotonic()
    _, stderr = proc.communicate(timeout=300)
    took = time.monotonic() - started
    assert proc.returncode == 0, stderr
    pd.testing.assert_frame_equal(steps_of(out / "small"), reference, check_exact=True)
    return took


# `make test` kills 4 times (one instant in each quarter of the batch, one of them SIGTERM),
# `make test-all` (heavy) 10 times: each trial is a fresh command and its resume (about 5 s).
@pytest.mark.parametrize(
    "trials", [4, pytest.param(10, marks=pytest.mark.heavy)], ids=["4-instants", "10-instants"]
)
def test_kill_at_random_instants_then_resume_gives_the_same_result(
    scenario, batch_seconds, tmp_path, trials
) -> None:
    """Stratified random instants over the whole batch (runs, their saving, the final writes),
    so that every phase is hit; every third trial sends SIGTERM instead of SIGKILL. One job:
    the command does the writing (killing a parent with workers: the test above and
    test_interrupt)."""
    path, reference = scenario
    rng = random.Random(11)
    span = 0.8 * batch_seconds  # the last fifth is the interpreter ending
    phases = []
    for i in range(trials):
        at = (i + rng.random()) / trials * span
        sig = signal.SIGTERM if i % 3 == 2 else signal.SIGKILL
        out = tmp_path / f"trial{i}"
        target = out / "small"
        proc = start(path, out, "--jobs", "1")
        try:
            assert wait_for_batch_start(proc), proc.communicate()
            try:
                proc.wait(timeout=at)  # finished before the instant: nothing to kill
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, sig)
            proc.communicate(timeout=60)
            wait_until_gone(proc.pid)
        finally:
            kill_group(proc)
        complete = (target / MANIFEST_FILE).exists()
        saved = sorted(int(p.name[4:10]) for p in (target / RUNS_DIR).glob("run-*.npz"))
        phases.append("complete" if complete else f"{len(saved)} saved")
        if not complete:
            rerun = cli("run", path, "--out", out, "--jobs", "1")
            assert rerun.exit_code == 0, (i, at, rerun.output)
            if saved:
                assert f"resuming: {len(saved)} of 6 runs" in rerun.stdout, rerun.stdout
                assert read_json(target / MANIFEST_FILE)["resumed_runs"] == saved
            assert not (target / RUNS_DIR).exists()
        pd.testing.assert_frame_equal(steps_of(target), reference, check_exact=True)
    print(f"kill instants over {span:.1f} s of batch: {phases}")
    assert any(p != "complete" for p in phases), phases
