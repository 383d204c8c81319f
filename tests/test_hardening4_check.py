"""Hardening 4 (issues 32 and 38): `anfekf check` on edited and huge result files, a result of
another run count, hand-edited simulated manifests, write errors on stdout, and the fast paths of
the command line (docs/HARDENING.md, "Hardening 4")."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from anfekf_bench.analysis import gate
from anfekf_bench.storage import COMPARISONS_FILE, MANIFEST_FILE, write_parquet

from .conftest import small_scenario, write_scenario
from .test_check import _fail_lines, check, claim, paper_like, write_results
from .test_confinement import SMALL, assert_one_line_error, cli

CLAIM = "anfekf rmse_pos <= 0.6 x ekf"  # what write_results declares in every scenario


def _comparison(estimate: float, lo: float, hi: float, **keys) -> dict:
    """One comparisons.parquet row as `anfekf run` writes it."""
    row = {"scenario": "wrong_r", "filter": "anfekf", "vs": "ekf", "metric": "rmse_pos",
           "kind": "ratio", "runs_used": 20, "estimate": estimate, "lo": lo, "hi": hi,
           "method": "BCa", "p_value": 0.01, "test": "Wilcoxon signed-rank"}  # fmt: skip
    return {**row, **keys}


def _results_with(tmp_path: Path, comparisons: list[dict] | None, claims: list[dict]) -> Path:
    results = write_results(tmp_path / "res", {"wrong_r": paper_like()["wrong_r"]},
                            claims={"wrong_r": claims})  # fmt: skip
    if comparisons is not None:
        write_parquet(results / "wrong_r" / COMPARISONS_FILE, pd.DataFrame(comparisons))
    return results


HOLDS = claim(CLAIM, "holds", 0.5, 0.45, 0.55)

# id: (comparisons.parquet rows or None, claims.json records, words of the one-line error). On
# main each of these "held" (exit 0): the interval was decided on whatever it said.
BAD_INTERVALS = {
    "comparison-inverted": ([_comparison(0.5, 1.9, 0.1)], [HOLDS], "inverted"),
    "comparison-estimate-outside": ([_comparison(5.0, 0.1, 0.2)], [HOLDS], "outside its interval"),
    "comparison-infinite": ([_comparison(0.5, -math.inf, 0.55)], [HOLDS], "finite numbers"),
    "comparison-half-interval": ([_comparison(0.5, math.nan, 0.55)], [HOLDS], "both null"),
    "comparison-second-failing-row": (
        [_comparison(0.5, 0.45, 0.55), _comparison(0.7, 0.65, 0.8)],
        [HOLDS],
        "second row",
    ),
    "claims-json-inverted": (None, [claim(CLAIM, "holds", 0.5, 1.9, 0.1)], "inverted"),
    "claims-json-estimate-outside": (
        None,
        [claim(CLAIM, "holds", 5.0, 0.1, 0.2)],
        "outside its interval",
    ),
    "claims-json-second-different-record": (
        None,
        [HOLDS, claim(CLAIM, "fails", 0.7, 0.65, 0.8)],
        "second, different result",
    ),
}


@pytest.mark.parametrize("comparisons, claims, words", BAD_INTERVALS.values(), ids=BAD_INTERVALS)
def test_an_edited_interval_is_refused_before_any_claim_is_decided(
    tmp_path, comparisons, claims, words
):
    results = _results_with(tmp_path, comparisons, claims)
    where = COMPARISONS_FILE if comparisons is not None else "claims.json"
    assert_one_line_error(check(results), where, words)


def test_what_anfekf_run_writes_without_an_interval_still_decides(tmp_path):
    """Null bounds (a share, too few runs, a biased bootstrap) and a declared claim written
    twice are what `anfekf run` writes: inconclusive, not refused."""
    point = claim(CLAIM, "inconclusive", 0.5, None, None)
    results = _results_with(tmp_path, [_comparison(0.5, math.nan, math.nan)], [point, point])
    result = check(results)
    assert result.exit_code == 0, result.output
    assert "1 inconclusive" in result.output or "2 inconclusive" in result.output


def _many_claims(tmp_path: Path, n: int) -> Path:
    """One scenario declaring `n` claims (thresholds apart), each decided on its comparison."""
    results = _results_with(tmp_path, [_comparison(0.5, 0.45, 0.55)], [HOLDS])
    path = results / "wrong_r" / MANIFEST_FILE
    manifest = json.loads(path.read_text())
    manifest["scenario"]["claims"] = [
        {"filter": "anfekf", "vs": "ekf", "metric": "rmse_pos", "at_most": 0.5 + i * 1e-5}
        for i in range(n)
    ]
    path.write_text(json.dumps(manifest))
    return results


def test_the_comparisons_file_is_read_once_per_scenario(tmp_path, monkeypatch):
    """It was read (and filtered) once per claim: 10,000 claims took minutes."""
    results = _many_claims(tmp_path, 50)
    read = []
    real = gate.read_parquet
    monkeypatch.setattr(gate, "read_parquet", lambda p: read.append(Path(p).name) or real(p))
    result = check(results)
    assert result.exit_code == 0, result.output
    assert read.count(COMPARISONS_FILE) == 1, read


def test_ten_thousand_claims_take_seconds(tmp_path):
    results = _many_claims(tmp_path, 10_000)
    started = time.perf_counter()
    result = check(results)
    took = time.perf_counter() - started
    assert result.exit_code == 0, result.output
    assert "claims hold" in result.output
    assert took < 60, f"{took:.1f} s (it was minutes)"


def test_a_huge_baseline_draws_a_bounded_table_and_every_fail_line(tmp_path):
    results = write_results(tmp_path / "res", {"wrong_r": paper_like()["wrong_r"]})
    baseline = tmp_path / "ci.json"
    assert check(results, "--baseline", baseline, "--update").exit_code == 0
    doc = json.loads(baseline.read_text())
    guarded = doc["scenarios"]["wrong_r"]
    for i in range(1000):
        doc["scenarios"][f"gone{i:04d}"] = guarded
    baseline.write_text(json.dumps(doc))
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1, result.output
    drawn = [line for line in result.output.splitlines() if line.startswith("│")]
    assert len(drawn) <= gate.TABLE_ROWS + 10, len(drawn)
    assert "failing rows only" in result.output
    assert len(_fail_lines(result.output)) == 1000


def test_results_of_another_run_count_are_not_judged_metric_by_metric(tmp_path):
    """A 50-run result against the 20-run baseline: not comparable, said once per scenario with
    what to do; no worse/better rows that mean nothing, no bare advice to --update."""
    results = write_results(tmp_path / "res", paper_like())
    baseline = tmp_path / "ci.json"
    assert check(results, "--baseline", baseline, "--update").exit_code == 0
    moved = paper_like()
    moved["wrong_r"]["ekf"]["rmse_pos"] *= 2  # beyond tolerance: a row "worse" on main
    write_results(results, moved, runs=50)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1, result.output
    out = result.output
    for word in ("worse", "better", "within tolerance", "if the change is intended"):
        assert word not in out, (word, out)
    fails = _fail_lines(out)
    assert len(fails) == 4, fails
    assert all("not comparable" in f and "--runs 20" in f for f in fails), fails
    assert "deliberately" in out and "--update" in out


def test_escape_sequences_in_a_baseline_are_printed_escaped(tmp_path):
    results = write_results(tmp_path / "res", {"wrong_r": paper_like()["wrong_r"]})
    baseline = tmp_path / "ci.json"
    assert check(results, "--baseline", baseline, "--update").exit_code == 0
    doc = json.loads(baseline.read_text())
    doc["scenarios"]["\x1b[2J\x1b[31mpwn"] = doc["scenarios"]["wrong_r"]
    baseline.write_text(json.dumps(doc))
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1, result.output
    assert "\x1b" not in result.output
    assert "\\x1b[2J\\x1b[31mpwn" in result.output


# --- Hand-edited simulated manifests (last turn fixed these for recorded ones only) ---------------


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """A complete result of the small scenario (2 runs), made once."""
    from anfekf_bench.experiment import execute, make_plan
    from anfekf_bench.scenarios import load_scenario

    root = tmp_path_factory.mktemp("simulated")
    path = write_scenario(root / "small.yaml", small_scenario(**SMALL))
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), root / "out")
    return target


def _edited_copy(previous: Path, tmp_path: Path, edit) -> Path:
    import shutil

    folder = tmp_path / "res" / previous.name
    shutil.copytree(previous, folder)
    path = folder / MANIFEST_FILE
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    return folder


def _all_landmarks_at(value: float):
    def edit(doc):
        doc["world"]["landmarks"] = [[value, value] for _ in doc["world"]["landmarks"]]

    return edit


def _two_waypoints_far_apart(doc):
    doc["world"]["waypoints"][:2] = [[-1e308, -1e308], [1e308, 1e308]]


def _lone_surrogate(doc):
    doc["scenario"]["description"] = "\ud800"


SIMULATED_EDITS = {
    "landmarks-1e308": (_all_landmarks_at(1e308), "world.landmarks"),  # OverflowError
    "waypoints-plus-minus-1e308": (_two_waypoints_far_apart, "world.waypoints"),  # ValueError
    "description-lone-surrogate": (_lone_surrogate, "not valid Unicode"),  # UnicodeEncodeError
}


@pytest.mark.parametrize("edit", list(SIMULATED_EDITS))
@pytest.mark.parametrize("command", ["report", "check"])
def test_a_hand_edited_simulated_manifest_is_one_line(simulated, tmp_path, edit, command):
    change, words = SIMULATED_EDITS[edit]
    folder = _edited_copy(simulated, tmp_path, change)
    args = ("--out", tmp_path / "report") if command == "report" else ()
    assert_one_line_error(cli(command, folder, *args), str(folder / MANIFEST_FILE), words)


# --- Output that cannot be written ------------------------------------------------------------

ENTRY = [sys.executable, "-c", "from anfekf_bench.entry import main; main()"]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
@pytest.mark.parametrize(
    "args", [["kinds"], ["--version"], ["-h"], ["init", "{tmp}/new.yaml"], ["check", "{res}"]]
)
def test_a_full_stdout_is_one_line_and_a_nonzero_exit(tmp_path, args):
    """`anfekf kinds > /dev/full` was rich's traceback (exit 1): every printing command."""
    results = write_results(tmp_path / "res", {"wrong_r": paper_like()["wrong_r"]})
    argv = [a.format(tmp=tmp_path, res=results) for a in args]
    with open("/dev/full", "w") as full:
        done = subprocess.run([*ENTRY, *argv], stdout=full, stderr=subprocess.PIPE, text=True,
                              timeout=120)  # fmt: skip
    lines = done.stderr.splitlines()
    assert done.returncode == 74, (done.returncode, done.stderr[-2000:])
    assert lines == ["error: standard output: cannot write ([Errno 28] No space left on device)"]


# --- Dask: a scheduler killed mid-batch -----------------------------------------------------------


def test_distributed_loggers_are_all_quiet_once_connected():
    """distributed's config gives distributed.client (WARNING) and tornado.application (ERROR)
    levels and handlers of their own: quieting their parents left their ERROR line and asyncio
    traceback on stderr before our one line when the scheduler was killed."""
    import logging

    pytest.importorskip("distributed")
    from anfekf_bench.runner import _quiet_dask_logs

    _quiet_dask_logs()
    for name in ("distributed", "distributed.client", "distributed.core", "tornado.application",
                 "asyncio", "distributed.comm.tcp"):  # fmt: skip
        assert not logging.getLogger(name).isEnabledFor(logging.CRITICAL), name


@pytest.mark.slow
def test_kill_9_of_the_scheduler_is_our_one_line_only(tmp_path):
    """A scheduler and a worker in processes of their own, `anfekf run` on them, kill -9 of the
    scheduler once the batch runs: stderr holds our one line, nothing of distributed's."""
    import signal
    import socket

    pytest.importorskip("distributed")
    from .conftest import small_scenario, write_scenario

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    scheduler = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler",
                                  "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                                 **quiet)  # fmt: skip
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address,
                               "--nthreads", "1", "--no-nanny"], **quiet)  # fmt: skip
    try:
        doc = small_scenario(name="dk", runs=200, backend={"kind": "dask", "scheduler": address,
                                                           "connect_timeout_s": 60})  # fmt: skip
        path = write_scenario(tmp_path / "dk.yaml", doc)
        pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
        run = subprocess.Popen([*ENTRY, "run", str(path), "--out", str(tmp_path / "o")], **pipes)
        store = tmp_path / "o" / "dk" / ".runs"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list(store.glob("run-*.npz"))) < 2:
            assert run.poll() is None, run.communicate()
            time.sleep(0.2)
        scheduler.send_signal(signal.SIGKILL)
        _, err = run.communicate(timeout=180)
    finally:
        for proc in (scheduler, worker):
            if proc.poll() is None:
                proc.kill()
            proc.wait()
    assert run.returncode == 2, err
    assert err.splitlines() == [
        f"error: Dask cluster at {address} failed during the batch (connection lost); finished"
        " runs are saved: run the same command again to resume"
    ], err


def test_the_one_worker_cluster_has_its_worker_before_a_test_starts():
    """The tests on it gave the worker's process 2 s to start (connect_dask(address, 2.0)): under
    load its import alone took longer. The fixture now waits for the worker to register."""
    pytest.importorskip("distributed")
    from .conftest import cluster_with_one_worker

    with cluster_with_one_worker() as (address, _worker):
        from distributed import Client

        with Client(address, timeout=60, set_as_default=False) as client:
            assert client.scheduler_info()["workers"], "no worker registered yet"


# --- The command line's fast paths; `anfekf kinds NAME` ---------------------------------------

HEAVY = ("numpy", "pandas", "scipy", "numba", "matplotlib", "pyarrow")


def _modules_after(*args: str) -> list[str]:
    """The heavy modules imported by `anfekf ARGS`, run in a fresh interpreter."""
    code = (
        "import sys\nfrom anfekf_bench.cli import app\n"
        f"try:\n    app({list(args)!r})\nexcept SystemExit:\n    pass\n"
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return eval(done.stdout.strip().splitlines()[-1])  # a list literal we printed


@pytest.mark.parametrize("args", [["--version"], ["-h"], ["run", "-h"]])
def test_version_and_help_import_nothing_heavy(args):
    """They imported numpy, pandas, scipy, numba and matplotlib: about 3 s of CPU each."""
    assert _modules_after(*args) == []


def test_kinds_imports_no_compiler_nor_plots():
    assert not {"numba", "matplotlib", "pandas"} & set(_modules_after("kinds"))


def test_kinds_shows_the_kinds_named_and_refuses_an_unknown_one():
    shown = cli("kinds", "anfekf", "sage-husa")
    assert shown.exit_code == 0, shown.output
    heads = [line.split(":")[0] for line in shown.stdout.splitlines() if not line.startswith(" ")]
    assert heads == ["anfekf", "sage-husa"]
    line = assert_one_line_error(cli("kinds", "anfekf", "bogus"), "'bogus'", "known: ekf,")
    assert "kalmannet" in line


# --- The fast engine's first compilation is announced ----------------------------------------

COMPILING = "compiling the fast engine's kernels once"


@pytest.mark.parametrize("cached", [False, True, None])
def test_the_compile_line_shows_only_when_the_kernels_are_not_cached(tmp_path, monkeypatch, cached):
    from anfekf_bench.engines import fast

    compiled = []
    monkeypatch.setattr(fast, "kernels_cached", lambda: cached)
    monkeypatch.setattr(fast, "warm_up", lambda: compiled.append(1) or 0.0)
    path = write_scenario(tmp_path / "s.yaml", small_scenario(engine="fast", **SMALL))
    done = cli("run", path, "--out", tmp_path / "o")
    assert done.exit_code == 0, done.output
    shown = [line for line in done.stderr.splitlines() if COMPILING in line]
    assert len(shown) == (cached is False) and len(compiled) == (cached is False), done.stderr


def test_an_empty_numba_cache_is_seen_as_cold(tmp_path):
    """A fresh interpreter on an empty NUMBA_CACHE_DIR (numba reads it at import)."""
    from anfekf_bench.engines import kernels

    if not kernels.JIT:
        pytest.skip("numba is not installed: nothing is compiled")
    code = "from anfekf_bench.engines import fast; print(fast.kernels_cached())"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300)  # fmt: skip
    assert done.stdout.strip().splitlines()[-1] == "False", done.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.heavy
def test_the_first_fast_run_says_it_compiles_and_the_second_does_not(tmp_path):
    """End to end on an empty numba cache: the line, the compilation (a minute or two), then a
    second run that loads the cache and says nothing."""
    from anfekf_bench.engines import kernels

    if not kernels.JIT:
        pytest.skip("numba is not installed: nothing is compiled")
    path = write_scenario(tmp_path / "s.yaml", small_scenario(engine="fast", **SMALL))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    errs = []
    for _ in range(2):
        done = subprocess.run([*ENTRY, "run", str(path), "--out", str(tmp_path / "o"), "--force"],
                              capture_output=True, text=True, env=env, timeout=900)  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        errs.append(done.stderr)
    assert sum(COMPILING in line for line in errs[0].splitlines()) == 1, errs[0]
    assert COMPILING not in errs[1], errs[1]
