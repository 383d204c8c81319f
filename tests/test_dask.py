"""Issue 8: running the Monte Carlo batch on a Dask distributed cluster through joblib.

The cluster test starts a real `distributed.LocalCluster` (two worker processes on 127.0.0.1) and
checks that `anfekf run --backend dask` writes exactly the bytes-equal tables of the local run.
"""

from __future__ import annotations

import json
import socket
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import BackendConfig, parse_scenario
from anfekf_bench.experiment import make_plan
from anfekf_bench.runner import BackendUnavailable, connect_dask, run_batch
from anfekf_bench.scenarios import load_scenario

from .conftest import cluster_with_one_worker

distributed = pytest.importorskip("distributed")

# A second scheduler (or another project's) finds the default HTTP port taken and picks another.
pytestmark = pytest.mark.filterwarnings("ignore:Port 8787 is already in use:UserWarning")

RUNS = 4


def tiny_scenario(**overrides) -> dict:
    """A ~45 m route past six landmarks: each run takes well under a second."""
    doc = {
        "name": "tiny",
        "seed": 11,
        "runs": RUNS,
        "jobs": 2,
        "record_every": 8,
        "world": {
            "landmarks": [[10, 8], [25, -6], [40, 16], [30, 15], [15, -10], [48, 4]],
            "waypoints": [[20, 0], [40, 10]],
        },
        "filter_noise": {"sigma_range": 2.0, "sigma_bearing_deg": 0.1},
        "filters": [
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
        ],
    }
    doc.update(overrides)
    return doc


def write_yaml(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def unused_port() -> int:
    """A local TCP port nobody listens on (bound, read, released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def scheduler() -> str:
    """Address of a two-process LocalCluster, shut down after this module."""
    cluster = distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    )
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def finished_run_tasks(address: str) -> set[str]:
    """Keys of the `run_chunk` tasks the scheduler has seen finish (reach memory)."""
    with distributed.Client(address, set_as_default=False) as client:
        return set(client.run_on_scheduler(_finished_run_keys))


def _finished_run_keys(dask_scheduler) -> list[str]:
    # transition_log entries: (key, start state, finish state, recommendations, stimulus, time)
    return [
        str(entry[0])
        for entry in dask_scheduler.transition_log
        if "run_chunk" in str(entry[0]) and entry[2] == "memory"
    ]


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_dask_run_equals_local_run(tmp_path: Path, scheduler: str) -> None:
    scenario = write_yaml(tmp_path / "tiny.yaml", tiny_scenario())
    on_dask = invoke(
        "run", scenario, "--out", tmp_path / "dask", "--backend", "dask", "--scheduler", scheduler
    )
    assert on_dask.exit_code == 0, on_dask.output
    assert f"{RUNS}/{RUNS}" in on_dask.stdout  # the progress bar reached the end
    local = invoke("run", scenario, "--out", tmp_path / "local")
    assert local.exit_code == 0, local.output

    dask_dir, local_dir = tmp_path / "dask" / "tiny", tmp_path / "local" / "tiny"
    steps = pd.read_parquet(dask_dir / "steps.parquet")
    assert sorted(steps["run"].unique()) == list(range(RUNS))
    pd.testing.assert_frame_equal(
        steps, pd.read_parquet(local_dir / "steps.parquet"), check_exact=True
    )
    pd.testing.assert_frame_equal(
        pd.read_parquet(dask_dir / "summary.parquet"),
        pd.read_parquet(local_dir / "summary.parquet"),
        check_exact=True,
    )
    assert (dask_dir / "summary.json").read_text() == (local_dir / "summary.json").read_text()

    dask_manifest = json.loads((dask_dir / "manifest.json").read_text())
    local_manifest = json.loads((local_dir / "manifest.json").read_text())
    assert dask_manifest["backend"]["kind"] == "dask"
    assert dask_manifest["backend"]["scheduler"] == scheduler
    assert local_manifest["backend"]["kind"] == "local"
    assert dask_manifest["fingerprint"] == local_manifest["fingerprint"]


def test_dask_batch_reports_each_run_and_skips_done_ones(tmp_path: Path, scheduler: str) -> None:
    scenario, world = load_scenario(write_yaml(tmp_path / "tiny.yaml", tiny_scenario()))
    seen: list[int] = []
    common = {"runs": RUNS, "seed": 5, "jobs": 2, "skip": {1}}
    before = finished_run_tasks(scheduler)
    on_dask = {
        r["run"]: r
        for r in run_batch(
            scenario,
            world,
            **common,
            on_result=lambda r: seen.append(r["run"]),
            backend="dask",
            scheduler=scheduler,
        )
    }
    assert sorted(seen) == sorted(on_dask) == [0, 2, 3]
    # The runs really went to the cluster, one Dask task per run (so progress moves per run).
    assert len(finished_run_tasks(scheduler) - before) == 3
    local = {r["run"]: r for r in run_batch(scenario, world, **common)}
    for run, result in on_dask.items():
        for name in ("ekf", "anfekf"):
            for key in ("x", "P", "R_diag", "nees"):
                np.testing.assert_array_equal(
                    result["filters"][name][key], local[run]["filters"][name][key]
                )


@pytest.mark.slow  # two runs of a recorded log, each with its tuning: about 15 s
def test_recorded_log_on_dask_equals_local_run(tmp_path: Path, scheduler: str) -> None:
    """A recorded log's held-out segments go through the same dispatch as simulated runs: on
    the cluster (one Dask task per segment) they write exactly the local run's tables."""
    from .test_real_data import user_scenario

    path = user_scenario(tmp_path)
    before = finished_run_tasks(scheduler)
    on_dask = invoke(
        "run", path, "--out", tmp_path / "dask", "--backend", "dask", "--scheduler", scheduler
    )
    assert on_dask.exit_code == 0, on_dask.output
    assert len(finished_run_tasks(scheduler) - before) == 2  # both segments ran there
    local = invoke("run", path, "--out", tmp_path / "local")
    assert local.exit_code == 0, local.output

    dask_dir, local_dir = tmp_path / "dask" / "my-robot", tmp_path / "local" / "my-robot"
    for table in ("steps", "runs", "summary", "comparisons"):
        pd.testing.assert_frame_equal(
            pd.read_parquet(dask_dir / f"{table}.parquet"),
            pd.read_parquet(local_dir / f"{table}.parquet"),
            check_exact=True,
        )
    for doc in ("summary.json", "claims.json"):
        assert (dask_dir / doc).read_text() == (local_dir / doc).read_text()
    dask_manifest = json.loads((dask_dir / "manifest.json").read_text())
    local_manifest = json.loads((local_dir / "manifest.json").read_text())
    assert dask_manifest["kind"] == local_manifest["kind"] == "recorded"
    assert dask_manifest["backend"] == {"kind": "dask", "scheduler": scheduler,
                                        "connect_timeout_s": 10.0}  # fmt: skip
    assert local_manifest["backend"]["kind"] == "local"
    assert dask_manifest["fingerprint"] == local_manifest["fingerprint"]
    assert dask_manifest["tuning"]["sigma_v"] == local_manifest["tuning"]["sigma_v"]


def test_recorded_plan_takes_the_backend_overrides(tmp_path: Path) -> None:
    """One make_plan for every source: a recorded scenario's plan takes --backend dask and
    --scheduler like a simulated one's (its resume fingerprint does not depend on them)."""
    from anfekf_bench.real_experiment import RecordedSource

    from .test_real_data import user_scenario

    scenario, recording = load_scenario(user_scenario(tmp_path))
    plan = make_plan(scenario, recording, None, None, None, backend="dask", scheduler="tcp://h:1")
    assert isinstance(plan.source, RecordedSource) and plan.runs == 2
    assert plan.backend == BackendConfig(kind="dask", scheduler="tcp://h:1")
    local = make_plan(scenario, recording, None, None, None)
    assert local.backend.kind == "local" and local.engine == "filterpy"
    assert plan.fingerprint() == local.fingerprint()
    fast = make_plan(scenario, recording, None, None, None, engine="fast")
    assert fast.fingerprint() != local.fingerprint()  # the engine changes a run's bytes


def test_a_recorded_scenario_file_sets_engine_and_backend_as_a_simulated_one_does(tmp_path: Path):
    """engine: and backend: are keys of every scenario file; the command line overrides them."""
    import yaml

    from .test_real_data import user_scenario

    path = user_scenario(tmp_path)
    doc = yaml.safe_load(path.read_text())
    doc.update(engine="fast", backend={"kind": "dask", "scheduler": "tcp://h:1"})
    write_yaml(path, doc)
    scenario, recording = load_scenario(path)
    plan = make_plan(scenario, recording, None, None, None)
    assert plan.engine == "fast" and plan.backend.scheduler == "tcp://h:1"
    local = make_plan(scenario, recording, None, None, None, backend="local", engine="filterpy")
    assert local.engine == "filterpy" and local.backend.kind == "local"
    doc["engine"] = "turbo"
    result = invoke("run", write_yaml(path, doc), "--out", tmp_path / "out")
    assert result.exit_code == 2 and "engine" in result.stderr and "Traceback" not in result.output


def test_unreachable_scheduler_is_one_line_within_timeout(tmp_path: Path) -> None:
    address = f"tcp://127.0.0.1:{unused_port()}"
    doc = tiny_scenario(backend={"kind": "dask", "scheduler": address, "connect_timeout_s": 2})
    result = invoke("run", write_yaml(tmp_path / "tiny.yaml", doc), "--out", tmp_path / "out")
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert lines == [f"error: cannot reach Dask scheduler at {address}: no answer (timeout 2 s)"]
    assert not (tmp_path / "out" / "tiny" / "manifest.json").exists()


def test_scheduler_without_workers_is_reported() -> None:
    cluster = distributed.LocalCluster(
        n_workers=0, processes=True, host="127.0.0.1", dashboard_address=None
    )
    try:
        with pytest.raises(BackendUnavailable, match="has no workers after 1 s"):
            connect_dask(cluster.scheduler_address, 1.0)
    finally:
        cluster.close()


def test_cluster_lost_mid_batch_is_reported(tmp_path: Path) -> None:
    # One single-threaded worker: joblib alone would run such a batch in this process instead.
    scenario, world = load_scenario(write_yaml(tmp_path / "tiny.yaml", tiny_scenario()))
    cluster = distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    )
    try:
        batch = run_batch(
            scenario,
            world,
            runs=6,
            seed=1,
            jobs=2,
            backend="dask",
            scheduler=cluster.scheduler_address,
            connect_timeout_s=1,
        )
        next(batch)
    finally:
        cluster.close()  # with 5 runs still to come
    with pytest.raises(BackendUnavailable, match=r"failed during the batch \(connection lost\)"):
        list(batch)


def test_missing_dask_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # makes `import distributed` fail
    with pytest.raises(BackendUnavailable, match=r'pip install -e "\.\[dask\]"'):
        connect_dask("tcp://127.0.0.1:8786", 1.0)


@pytest.mark.parametrize(
    ("file_backend", "flags", "message"),
    [
        pytest.param(
            None,
            ["--scheduler", "tcp://127.0.0.1:8786"],
            "--scheduler tcp://127.0.0.1:8786: only used with --backend dask",
            id="scheduler-without-dask",
        ),
        pytest.param(
            None,
            ["--backend", "local", "--scheduler", "tcp://127.0.0.1:8786"],
            "only used with --backend dask",
            id="scheduler-with-local",
        ),
        pytest.param(
            None,
            ["--backend", "dask"],
            "--backend dask needs --scheduler",
            id="dask-without-scheduler",
        ),
        pytest.param(
            None,
            ["--backend", "dask", "--scheduler", "127.0.0.1:8786"],
            "expected a Dask scheduler address like tcp://HOST:PORT",
            id="address-without-protocol",
        ),
        pytest.param(None, ["--backend", "slurm"], "slurm", id="unknown-backend"),
        pytest.param(
            {"kind": "dask"},
            [],
            "backend: kind dask needs a scheduler",
            id="file-dask-without-scheduler",
        ),
        pytest.param(
            {"kind": "local", "scheduler": "tcp://h:8786"},
            [],
            "backend: scheduler is only used with kind dask",
            id="file-local-scheduler",
        ),
        pytest.param(
            {"kind": "dask", "address": "tcp://h:8786"},
            [],
            "backend.address: unknown key (allowed: connect_timeout_s, kind, scheduler)",
            id="file-unknown-key",
        ),
        pytest.param(
            {"kind": "dask", "scheduler": "h:8786"},
            [],
            "backend.scheduler",
            id="file-address-without-protocol",
        ),
        pytest.param(
            {"kind": "dask", "scheduler": "tcp://h:8786", "connect_timeout_s": 0},
            [],
            "backend.connect_timeout_s",
            id="file-zero-timeout",
        ),
    ],
)
def test_bad_backend_choice_exits_2_before_running(
    tmp_path: Path, file_backend: dict | None, flags: list[str], message: str
) -> None:
    doc = tiny_scenario() if file_backend is None else tiny_scenario(backend=file_backend)
    scenario = write_yaml(tmp_path / "tiny.yaml", doc)
    result = invoke("run", scenario, "--out", tmp_path / "out", *flags)
    assert result.exit_code == 2
    assert message in result.stderr
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("file_backend", "flags", "expected"),
    [
        pytest.param(None, {}, ("local", None), id="default-local"),
        pytest.param(
            None,
            {"backend": "dask", "scheduler": "tcp://h:1"},
            ("dask", "tcp://h:1"),
            id="flags-choose-dask",
        ),
        pytest.param(
            {"kind": "dask", "scheduler": "tcp://f:2"},
            {},
            ("dask", "tcp://f:2"),
            id="file-chooses-dask",
        ),
        pytest.param(
            {"kind": "dask", "scheduler": "tcp://f:2"},
            {"scheduler": "tcp://h:1"},
            ("dask", "tcp://h:1"),
            id="flag-overrides-file-address",
        ),
        pytest.param(
            {"kind": "dask", "scheduler": "tcp://f:2"},
            {"backend": "local"},
            ("local", None),
            id="flag-overrides-file-kind",
        ),
    ],
)
def test_flags_override_the_file_and_leave_the_fingerprint(
    tmp_path: Path, file_backend: dict | None, flags: dict, expected: tuple
) -> None:
    doc = tiny_scenario() if file_backend is None else tiny_scenario(backend=file_backend)
    scenario, world = load_scenario(write_yaml(tmp_path / "tiny.yaml", doc))
    plan = make_plan(scenario, world, None, None, None, **flags)
    assert (plan.backend.kind, plan.backend.scheduler) == expected
    plain, _ = load_scenario(write_yaml(tmp_path / "plain.yaml", tiny_scenario()))
    assert plan.fingerprint() == make_plan(plain, world, None, None, None).fingerprint()


def test_file_timeout_survives_flag_override() -> None:
    scenario = parse_scenario(tiny_scenario(backend={"connect_timeout_s": 3}))
    plan_backend = make_plan(scenario, None, 1, 1, 1, backend="dask", scheduler="tcp://h:1").backend
    assert plan_backend == BackendConfig(kind="dask", scheduler="tcp://h:1", connect_timeout_s=3)


def test_results_finished_when_the_only_worker_dies_never_hang_the_batch() -> None:
    """Runs that finished on a worker, whose results were not fetched yet when it was killed:
    the batch ends (with those results, or with BackendUnavailable) within its watchdog's bound.
    Fetching a result only after its future was ready waited forever here (the scheduler
    recomputes the lost result, on no worker): CI hung once on it."""
    import threading
    import time

    from anfekf_bench.runner import _run_on_dask

    outcome: list = []
    with cluster_with_one_worker() as (address, worker):
        client = connect_dask(address, 2.0)
        batch = _run_on_dask(client, [(int, (str(i),), {}) for i in range(6)], address, 2.0)
        first = next(batch)
        time.sleep(1.0)  # the other five finish on the worker meanwhile
        worker.kill()
        worker.wait()

        def rest() -> None:
            try:
                outcome.append(sorted([first, *batch]))
            except BackendUnavailable as exc:
                outcome.append(str(exc))

        consumer = threading.Thread(target=rest, daemon=True)
        consumer.start()
        consumer.join(timeout=30)
        assert not consumer.is_alive(), "the batch still waits 30 s after its worker died"
    assert outcome[0] == list(range(6)) or "has had no workers for 2 s" in outcome[0], outcome


def test_an_error_inside_a_run_on_dask_keeps_its_type() -> None:
    """A run's own failure (a user's filter raising, say) is not taken for a lost cluster."""
    from anfekf_bench.runner import _run_on_dask

    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        client = connect_dask(cluster.scheduler_address, 5.0)
        batch = _run_on_dask(client, [(int, ("not a number",), {})], cluster.scheduler_address)
        with pytest.raises(ValueError, match="invalid literal for int"):
            list(batch)
