"""Interrupted runs (issue 7): nothing half-written looks complete; a rerun resumes or refuses.

Result files are written under a temporary name and renamed when complete (storage.write_atomic);
finished runs are saved one by one in <out>/<name>/.runs/; manifest.json is written last. A
rerun into the same folder resumes from the saved runs and says so; into a complete folder it
refuses unless --force.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.experiment import RUNS_DIR, execute, make_plan
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import (
    LOCK_FILE,
    MANIFEST_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    ResultsError,
    read_json,
    read_run_file,
    scenario_dirs,
    write_atomic,
)

from .conftest import live_group_members, small_scenario, write_scenario

COMPLETE_LOOKING = {STEPS_FILE, SUMMARY_PARQUET, SUMMARY_JSON, MANIFEST_FILE}


def cli(*args: str):
    return CliRunner().invoke(app, list(args))


def read_steps(folder: Path) -> pd.DataFrame:
    return pd.read_parquet(folder / STEPS_FILE)


def assert_nothing_looks_complete(target: Path, runs: int) -> list[int]:
    """Only the lock, the fingerprint, whole run files and *.tmp leftovers; returns the saved
    run ids."""
    saved = []
    fingerprint = (target / RUNS_DIR / "fingerprint").read_text().strip()
    for path in sorted(p for p in target.rglob("*") if p.is_file()):
        rel = path.relative_to(target).as_posix()
        assert path.name not in COMPLETE_LOOKING, f"{rel} exists after an interrupted run"
        if path.name.startswith(".") and path.name.endswith(".tmp"):
            continue  # an unfinished write: its name says so
        if rel in (f"{RUNS_DIR}/fingerprint", LOCK_FILE):
            continue
        assert rel.startswith(f"{RUNS_DIR}/run-") and rel.endswith(".npz"), rel
        result = read_run_file(path, fingerprint)  # a file under its final name is whole
        assert set(result) >= {"run", "step", "filters"}
        saved.append(result["run"])
    assert 0 < len(saved) < runs, f"kill came too late or too early: {len(saved)} of {runs}"
    with pytest.raises(ResultsError):  # report / check see no result here
        scenario_dirs(target.parent)
    return sorted(saved)


# --- A real process, killed -------------------------------------------------------------------

# Enough runs that the batch is still going when the first run file appears and the signal is
# sent: with 6, a faster harness sometimes finished the batch first (CI, one worker).
KILL_RUNS = 16


@pytest.fixture(scope="module")
def kill_scenario(tmp_path_factory) -> tuple[Path, pd.DataFrame]:
    """The default world, 2 filters, 16 runs (a few seconds); and its uninterrupted steps."""
    root = tmp_path_factory.mktemp("kill")
    doc = {
        "name": "killed",
        "seed": 11,
        "runs": KILL_RUNS,
        "jobs": 1,
        "record_every": 8,
        "filters": [{"name": "ekf", "kind": "ekf"}, {"name": "anfekf", "kind": "anfekf"}],
    }
    path = write_scenario(root / "killed.yaml", doc)
    _, target = execute(make_plan(*load_scenario(path), None, None, None), root / "reference")
    return path, read_steps(target)


def as_from_a_terminal() -> None:
    """Ctrl-C (and SIGTERM) as a shell's command gets it: at its default and not blocked. A test
    worker's mask or disposition is inherited by the command otherwise (in the full suite the
    command once went on to finish its batch, as if the signal had never come)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})


# How the command ends after each signal: its exit code and what it calls the stop.
STOPPED = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated (SIGTERM)")}


@pytest.mark.parametrize(
    ("sig", "jobs"),
    [(signal.SIGKILL, 2), (signal.SIGINT, 1), (signal.SIGTERM, 2)],
    ids=["kill-9-two-workers", "ctrl-c-one-worker", "sigterm-two-workers"],
)
def test_killed_run_leaves_nothing_complete_and_resumes(
    kill_scenario, tmp_path, monkeypatch, sig, jobs
):
    monkeypatch.setenv("ANFEKF_WORKER_START_S", "0")  # two jobs: workers, whatever runs cost
    path, reference = kill_scenario
    out = tmp_path / "out"
    target = out / "killed"
    command = "from anfekf_bench.cli import main; main()"
    args = [sys.executable, "-c", command, "run", str(path), "--out", str(out), "--jobs", str(jobs)]
    proc = subprocess.Popen(
        args,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=as_from_a_terminal,
    )
    try:
        deadline = time.monotonic() + 120
        while not list((target / RUNS_DIR).glob("run-*.npz")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no run finished within 120 s"
            time.sleep(0.01)
        assert proc.poll() is None, "the batch ended before it could be interrupted"
        os.killpg(proc.pid, sig)  # the whole group: the command and its joblib workers
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    time.sleep(0.2)
    assert live_group_members(proc.pid) == [], "worker processes outlived the command"

    saved = assert_nothing_looks_complete(target, KILL_RUNS)
    if sig in STOPPED:  # the whole group got it (as from systemd or a batch manager)
        code, word = STOPPED[sig]
        assert proc.returncode == code, stderr
        assert stderr.splitlines() == [
            f"error: killed: {word}; {len(saved)} of {KILL_RUNS} runs are saved in"
            f" {target / RUNS_DIR}: run the same command again to resume"
        ]
    else:
        assert proc.returncode == -signal.SIGKILL

    rerun = cli("run", str(path), "--out", str(out))
    assert rerun.exit_code == 0, rerun.output
    assert f"killed: resuming: {len(saved)} of {KILL_RUNS} runs" in rerun.stdout
    pd.testing.assert_frame_equal(read_steps(target), reference)
    assert read_json(target / MANIFEST_FILE)["resumed_runs"] == saved
    assert not (target / RUNS_DIR).exists()
    assert not list(target.glob(".*.tmp"))


# --- In-process interruptions (fast) ----------------------------------------------------------


class CtrlC(KeyboardInterrupt):
    """Raised from the progress callback: Ctrl-C after a given number of finished runs."""


def _interrupt_after(n: int):
    seen = []

    def on_result(result: dict) -> None:
        seen.append(result["run"])
        if len(seen) == n:
            raise CtrlC

    return on_result


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple[Path, pd.DataFrame]:
    """A 4-run small scenario and its uninterrupted steps (made once; tests only read them)."""
    root = tmp_path_factory.mktemp("small")
    path = write_scenario(root / "small.yaml", small_scenario(record_every=8))
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), root / "reference")
    return path, read_steps(target)


def test_ctrl_c_in_process_then_resume(small, tmp_path) -> None:
    path, reference = small
    plan = make_plan(*load_scenario(path), None, None, 1)
    out = tmp_path / "out"
    with pytest.raises(CtrlC):
        execute(plan, out, on_result=_interrupt_after(2))
    assert assert_nothing_looks_complete(out / "small", 4) == [0, 1]
    rerun = cli("run", str(path), "--out", str(out))
    assert rerun.exit_code == 0, rerun.output
    assert "small: resuming: 2 of 4 runs" in rerun.stdout
    pd.testing.assert_frame_equal(read_steps(out / "small"), reference)


def test_fast_batch_holds_its_first_seconds_and_saves_them_if_interrupted(small, tmp_path) -> None:
    """On the fast engine the runs of a batch's first seconds are held (outputs.RunStore): a
    batch that ends within them writes no run file; one interrupted there saves every run it
    held, and the resume says so and gives the uninterrupted result."""
    import anfekf_bench.experiment as experiment
    import anfekf_bench.outputs as outputs

    path, _ = small
    plan = make_plan(*load_scenario(path), None, None, 1, engine="fast")
    written = []
    real_save = outputs.save_run

    def counting_save(target, result, fingerprint):
        written.append(result["run"])
        real_save(target, result, fingerprint)

    reference = tmp_path / "reference"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(outputs, "save_run", counting_save)
        mp.setattr(experiment, "STORE_AFTER_S", 60.0)  # the batch's "first seconds", whatever
        # a loaded machine makes of its runs (and of loading the compiled kernels)
        _, target = execute(plan, reference)
        assert written == [], "a batch that ends within its first seconds saves no run"
        out = tmp_path / "out"
        with pytest.raises(CtrlC):
            execute(plan, out, on_result=_interrupt_after(3))
    assert sorted(written) == [0, 1, 2], "every run held when Ctrl-C came is saved"
    assert assert_nothing_looks_complete(out / "small", 4) == [0, 1, 2]
    rerun = cli("run", str(path), "--out", str(out), "--engine", "fast")
    assert rerun.exit_code == 0, rerun.output
    assert "small: resuming: 3 of 4 runs" in rerun.stdout
    pd.testing.assert_frame_equal(read_steps(out / "small"), read_steps(target))


# `anfekf run` on the fast engine whose run store holds every run (as in a batch's first
# seconds), and which, once it holds three, touches the file argv[1] names and waits.
HOLDS_THREE_THEN_WAITS = """
import pathlib, sys, time
import anfekf_bench.experiment as experiment, anfekf_bench.outputs as outputs
experiment.STORE_AFTER_S = 600.0
keep = outputs.RunStore.keep
marker = pathlib.Path(sys.argv.pop(1))
def keep_then_wait(self, result):
    keep(self, result)
    if len(self.held) == 3:
        marker.touch()
        time.sleep(120)
outputs.RunStore.keep = keep_then_wait
from anfekf_bench.cli import main
main()
"""


def test_sigterm_saves_the_runs_a_fast_batch_holds(small, tmp_path) -> None:
    """`kill PID` (SIGTERM, as `timeout`, `docker stop` or a batch manager send it) stops the
    command as a Ctrl-C does: the runs held in memory are saved, the message counts them, the
    exit code is 143, and the resume gives the uninterrupted tables. Its default action would
    lose them (signals.py)."""
    path, _ = small
    _, reference = execute(
        make_plan(*load_scenario(path), None, None, 1, engine="fast"), tmp_path / "reference"
    )
    out = tmp_path / "out"
    target = out / "small"
    marker = tmp_path / "holding-three"
    args = [sys.executable, "-c", HOLDS_THREE_THEN_WAITS, str(marker), "run", str(path),
            "--out", str(out), "--engine", "fast", "--jobs", "1"]  # fmt: skip
    proc = subprocess.Popen(
        args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=as_from_a_terminal,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "three runs not held within 120 s"
            time.sleep(0.01)
        assert not list((target / RUNS_DIR).glob("run-*.npz")), "the runs are held, not saved"
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, stderr
    assert stderr.splitlines() == [
        f"error: small: terminated (SIGTERM); 3 of 4 runs are saved in {target / RUNS_DIR}:"
        " run the same command again to resume"
    ]
    assert assert_nothing_looks_complete(target, 4) == [0, 1, 2]
    rerun = cli("run", str(path), "--out", str(out), "--engine", "fast")
    assert rerun.exit_code == 0, rerun.output
    assert "small: resuming: 3 of 4 runs" in rerun.stdout
    pd.testing.assert_frame_equal(read_steps(target), read_steps(reference))


def test_run_store_holds_until_its_time_then_saves_every_run(tmp_path, monkeypatch) -> None:
    import anfekf_bench.outputs as outputs

    saved = []
    monkeypatch.setattr(outputs, "save_run", lambda target, result, fp: saved.append(result["run"]))
    clock = [100.0]
    store = outputs.RunStore(tmp_path, "fp", hold_s=1.0, clock=lambda: clock[0])
    store.keep({"run": 0})
    clock[0] = 100.9
    store.keep({"run": 1})
    assert saved == [] and [r["run"] for r in store.held] == [0, 1]
    clock[0] = 101.0
    store.keep({"run": 2})
    assert saved == [0, 1, 2] and store.held == [], "the held runs go with the first after"
    store.keep({"run": 3})
    assert saved == [0, 1, 2, 3], "then each run at once"
    at_once = outputs.RunStore(tmp_path, "fp")  # hold_s 0: the filterpy engine's batches
    at_once.keep({"run": 4})
    assert saved[-1] == 4
    held = outputs.RunStore(tmp_path, "fp", hold_s=60.0)
    held.keep({"run": 5})
    held.flush()
    assert saved[-1] == 5 and held.held == []


def test_torn_run_file_and_stray_temporaries_are_redone(small, tmp_path) -> None:
    """A run file cut short (not by us: we rename) is redone; *.tmp leftovers are removed."""
    path, reference = small
    plan = make_plan(*load_scenario(path), None, None, 1)
    out = tmp_path / "out"
    target = out / "small"
    with pytest.raises(CtrlC):
        execute(plan, out, on_result=_interrupt_after(3))
    torn = target / RUNS_DIR / "run-000001.npz"
    torn.write_bytes(torn.read_bytes()[:100])
    (target / RUNS_DIR / ".run-000003.npz.abc123.tmp").write_bytes(b"half")
    (target / ".steps.parquet.def456.tmp").write_bytes(b"half")
    rerun = cli("run", str(path), "--out", str(out))
    assert rerun.exit_code == 0, rerun.output
    assert "resuming: 2 of 4 runs" in rerun.stdout
    assert "(1 saved run files refused and redone)" in rerun.stdout
    assert read_json(target / MANIFEST_FILE)["resumed_runs"] == [0, 2]
    pd.testing.assert_frame_equal(read_steps(target), reference)
    assert not [p for p in target.rglob("*.tmp")]


def test_complete_folder_refuses_then_force_overwrites(small, tmp_path) -> None:
    path, reference = small
    out = tmp_path / "out"
    first = cli("run", str(path), "--out", str(out))
    assert first.exit_code == 0 and "small: new results" in first.stdout
    before = (out / "small" / MANIFEST_FILE).read_bytes()

    again = cli("run", str(path), "--out", str(out))
    assert again.exit_code == 2
    assert len(again.stderr.splitlines()) == 1 and "--force" in again.stderr
    assert "complete result" in again.stderr
    assert (out / "small" / MANIFEST_FILE).read_bytes() == before, "refusing touches nothing"

    forced = cli("run", str(path), "--out", str(out), "--force")
    assert forced.exit_code == 0, forced.output
    assert "small: replacing the previous result" in forced.stdout
    pd.testing.assert_frame_equal(read_steps(out / "small"), reference)


def test_interrupted_folder_of_another_seed_refuses(small, tmp_path) -> None:
    path, _ = small
    plan = make_plan(*load_scenario(path), None, None, 1)
    out = tmp_path / "out"
    with pytest.raises(CtrlC):
        execute(plan, out, on_result=_interrupt_after(1))
    other = cli("run", str(path), "--out", str(out), "--seed", "99")
    assert other.exit_code == 2
    assert len(other.stderr.splitlines()) == 1
    assert "different scenario or seed" in other.stderr and "--force" in other.stderr
    assert len(list((out / "small" / RUNS_DIR).glob("run-*.npz"))) == 1, "nothing discarded"


def test_folder_killed_while_swapping_in_the_result_is_recomputed(small, tmp_path, monkeypatch):
    """Killed between the renames that swap a finished batch in (the old manifest already gone,
    some files replaced): not complete, and the run store is still there, so the same command
    resumes every run from it and writes the result again."""
    import anfekf_bench.storage as storage

    path, reference = small
    out = tmp_path / "out"
    renamed = []
    real_replace = os.replace

    def die_on_the_second_rename(src, dst):
        if Path(src).parent.name == "result" and Path(dst).parent.name == "small":
            if len(renamed) == 1:
                raise KeyboardInterrupt
            renamed.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(storage.os, "replace", die_on_the_second_rename)
    plan = make_plan(*load_scenario(path), None, None, 1)
    with pytest.raises(KeyboardInterrupt):
        execute(plan, out)
    monkeypatch.setattr(storage.os, "replace", real_replace)
    assert not (out / "small" / MANIFEST_FILE).exists()
    with pytest.raises(ResultsError, match="incomplete"):
        scenario_dirs(out)
    rerun = cli("run", str(path), "--out", str(out))
    assert rerun.exit_code == 0, rerun.output
    assert "small: resuming: 4 of 4 runs" in rerun.stdout
    pd.testing.assert_frame_equal(read_steps(out / "small"), reference)
    assert not (out / "small" / RUNS_DIR).exists()


@pytest.mark.parametrize("existing", [False, True], ids=["new-file", "replacing"])
def test_write_atomic_never_leaves_a_partial_file(tmp_path, existing: bool) -> None:
    target = tmp_path / "data.bin"
    if existing:
        target.write_bytes(b"old and whole")

    def write_half_then_die(tmp: Path) -> None:
        tmp.write_bytes(b"half of the ")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_atomic(target, write_half_then_die)
    assert sorted(p.name for p in tmp_path.iterdir()) == (["data.bin"] if existing else [])
    if existing:
        assert target.read_bytes() == b"old and whole"


def test_reference_result_is_self_consistent(small) -> None:
    """Guard for the tests above: the reference folder is complete and readable."""
    path, reference = small
    assert len(reference) > 0 and set(reference["run"]) == {0, 1, 2, 3}
    assert scenario_dirs(path.parent / "reference") == [path.parent / "reference" / "small"]
