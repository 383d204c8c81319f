"""End to end: simulation, seeding, Parquet output, the `run` command and its errors."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.analysis.tables import STEP_COLUMNS, steps_frame, update_statistics
from anfekf_bench.cli import app
from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.models import f
from anfekf_bench.runner import place_runs, runs_in_threads, simulated_run
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sources.simulator import simulate_run, simulate_truth
from anfekf_bench.storage import (
    LOCK_FILE,
    MANIFEST_FILE,
    STEPS_FILE,
    read_json,
    read_parquet,
    read_steps,
    write_parquet,
)

from .conftest import small_scenario, write_scenario

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
runner = CliRunner()


def test_default_world_drives_the_whole_route():
    _, world = load_scenario(CONFIGS / "correct.yaml")
    truth = simulate_truth(world)
    assert len(world.landmarks) == 35 and len(world.waypoints) == 17
    final = truth.x[-1, :2]
    assert np.hypot(*(final - world.waypoints[-1])) < world.waypoint_tolerance
    assert np.all(np.abs(truth.u[:, 1]) <= world.max_steer + 1e-12)
    assert np.all(np.abs(np.diff(truth.u[:, 1])) <= world.max_steer_rate * world.T + 1e-12)
    assert np.allclose(truth.u[:, 0], world.V)


def test_scans_are_at_the_sensor_rate_within_range_and_field_of_view():
    scenario, world = load_scenario(CONFIGS / "correct.yaml")
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(0))
    assert [s.step for s in data.scans[:3]] == [8, 16, 24]
    assert len(data.scans) == len(truth.u) // 8
    seen = np.array([len(s.ids) for s in data.scans])
    assert seen.max() >= 2 and 0 < np.mean(seen > 0) < 1  # sparse map: some scans see nothing
    for scan in data.scans[::50]:
        d = world.landmarks[scan.ids] - truth.x[scan.step, :2]
        assert np.all(np.hypot(d[:, 0], d[:, 1]) < world.max_range)
        assert np.all(np.abs(scan.z[:, 1]) < np.pi / 2 + 0.1)


def test_same_seed_same_data_other_seed_other_data():
    scenario = parse_scenario(small_scenario())
    world = resolve_world(scenario.world, Path("x.yaml"))
    seeds = np.random.SeedSequence(5).spawn(2)
    a = simulated_run(scenario, world, 0, seeds[0])
    b = simulated_run(scenario, world, 0, seeds[0])
    c = simulated_run(scenario, world, 1, seeds[1])
    np.testing.assert_array_equal(a["filters"]["ekf"]["x"], b["filters"]["ekf"]["x"])
    assert not np.allclose(a["filters"]["ekf"]["x"], c["filters"]["ekf"]["x"])


def _execute(tmp_path: Path, out: str, **overrides):
    path = write_scenario(tmp_path / f"{out}.yaml", small_scenario(**overrides))
    scenario, world = load_scenario(path)
    plan = make_plan(scenario, world, None, None, None)
    return execute(plan, tmp_path / out)


def test_results_do_not_depend_on_worker_count(tmp_path, monkeypatch):
    monkeypatch.setenv("ANFEKF_WORKER_START_S", "0")  # workers even for a batch this small
    _, one = _execute(tmp_path, "one", jobs=1, runs=4)
    _, two = _execute(tmp_path, "two", jobs=2, runs=4)
    pd.testing.assert_frame_equal(read_steps(one), read_steps(two), check_exact=True)
    assert (one / "steps.parquet").read_bytes() == (two / "steps.parquet").read_bytes()
    _, other = _execute(tmp_path, "other", jobs=2, runs=4, seed=8)
    assert not np.allclose(read_steps(one)["x_est"], read_steps(other)["x_est"])
    assert read_json(one / MANIFEST_FILE)["placement"]["where"] == "in-process"
    assert read_json(two / MANIFEST_FILE)["placement"]["where"] == "workers"


def test_fast_engine_runs_on_threads_with_the_same_bytes(tmp_path):
    """The fast engine's compiled runs go on `jobs` threads (no probe, no processes), with the
    same tables as on one job; a batch with one instance on filterpy keeps processes."""
    from anfekf_bench.engines import fast

    if not fast.JIT:
        pytest.skip("numba missing: the fast engine's kernels are plain Python")
    _, one = _execute(tmp_path, "one", jobs=1, runs=4, engine="fast")
    _, two = _execute(tmp_path, "two", jobs=2, runs=4, engine="fast")
    assert (one / "steps.parquet").read_bytes() == (two / "steps.parquet").read_bytes()
    assert read_json(two / MANIFEST_FILE)["placement"] == {"where": "threads", "workers": 2}
    assert read_json(one / MANIFEST_FILE)["placement"]["where"] == "in-process"
    assert runs_in_threads("fast", {"ekf": "fast", "anfekf": "fast"})
    assert not runs_in_threads("fast", {"ekf": "fast", "oracle": "filterpy"})
    assert not runs_in_threads("filterpy", {"ekf": "filterpy"})


def test_placement_from_measured_costs():
    """Workers when the runs' estimated cost pays for starting them, in-process otherwise."""
    small = place_runs(49, 2, run_s=0.01, start_s=2.0)  # 0.5 s here against 2.25 s on workers
    assert small["where"] == "in-process" and small["workers"] == 0
    assert small["estimate_in_process_s"] == pytest.approx(0.49)
    assert small["estimate_workers_s"] == pytest.approx(2.245)
    large = place_runs(49, 2, run_s=1.0, start_s=2.0)  # 49 s here against 26.5 s
    assert large["where"] == "workers" and large["workers"] == 2
    assert place_runs(49, 1, run_s=1.0)["where"] == "in-process"  # one job: never workers
    assert place_runs(1, 8, run_s=100.0, start_s=0.0)["where"] == "in-process"  # one run left
    assert place_runs(3, 8, run_s=1.0, start_s=0.0)["workers"] == 3  # at most one a run


def test_small_batch_runs_in_process(tmp_path, monkeypatch):
    monkeypatch.delenv("ANFEKF_WORKER_START_S", raising=False)
    path = write_scenario(tmp_path / "s.yaml", small_scenario(jobs=2, runs=3))
    scenario, world = load_scenario(path)
    _, target = execute(make_plan(scenario, world, None, None, None), tmp_path / "out")
    placement = read_json(target / MANIFEST_FILE)["placement"]
    assert placement["where"] == "in-process", placement
    assert placement["probe_run_s"] > 0


def test_output_files_and_columns(tmp_path):
    records, target = _execute(tmp_path, "out", runs=3, record_every=4)
    steps = read_steps(target)
    assert list(steps.columns) == STEP_COLUMNS
    assert set(steps["filter"]) == {"ekf", "anfekf", "ekf-oracle"}
    per = steps.groupby(["filter", "run"], observed=True).size()
    assert per.nunique() == 1 and len(per) == 9
    assert (steps["step"] % 4 == 0).all()
    np.testing.assert_allclose(steps["t"], steps["step"] * 0.025)
    manifest = json.loads((target / "manifest.json").read_text())
    assert manifest["runs"] == 3 and manifest["seed"] == 7
    assert manifest["scenario"]["name"] == "small" and "numpy" in manifest["versions"]
    summary = json.loads((target / "summary.json").read_text())
    assert [r["filter"] for r in summary] == ["ekf", "anfekf", "ekf-oracle"]
    table = pd.read_parquet(target / "summary.parquet").to_dict(orient="records")
    assert len(summary) == len(table)
    for rec_json, rec_pq in zip(summary, table, strict=True):
        assert rec_json == rec_pq
    assert not (target / ".runs").exists()
    ekf = steps[steps["filter"] == "ekf"]
    assert ekf["R_rr"].nunique() == 1 and ekf["R_rr"].iloc[0] == pytest.approx(4.0)
    ada = steps[steps["filter"] == "anfekf"]
    assert ada["R_rr"].iloc[-1] < 1.0  # R adapted down from the wrong 2 m towards 0.1 m


def test_parquet_round_trip(tmp_path):
    df = pd.DataFrame(
        {
            "scenario": pd.Categorical(["s", "s"]),
            "filter": pd.Categorical(["ekf", "anfekf"], categories=["ekf", "anfekf"]),
            "run": np.array([0, 1], dtype=np.int32),
            "nees": [1.5, np.nan],
            "diverged": [False, True],
        }
    )
    write_parquet(tmp_path / "x.parquet", df)
    back = read_parquet(tmp_path / "x.parquet")
    pd.testing.assert_frame_equal(back, df)
    assert not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize(
    "name, wrong, rmse_better_than_ekf",
    [("correct", {}, False), ("wrong_r", {"sigma_range": 2.0, "sigma_bearing_deg": 0.1}, True)],
    ids=["correct-noise", "wrong-R"],
)
def test_ekf_consistency_acceptance(tmp_path, name, wrong, rmse_better_than_ekf):
    """Correct noise, 20 runs: EKF NEES inside the 95 % bounds on >= 85 % of steps; wrong R: not."""
    doc = {
        "name": name,
        "seed": 11,
        "runs": 20,
        "jobs": 2,
        "record_every": 8,
        "filter_noise": wrong,
        "filters": [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-oracle", "kind": "ekf-oracle"}],
    }
    scenario, world = load_scenario(write_scenario(tmp_path / "s.yaml", doc))
    records, _ = execute(make_plan(scenario, world, None, None, None), tmp_path / "out")
    ekf, oracle = records
    assert ekf["nees_lo"] == pytest.approx(2.02, abs=0.005)
    assert oracle["nees_in_bounds"] >= 0.85
    if rmse_better_than_ekf:
        assert ekf["nees_in_bounds"] < 0.85
        assert oracle["rmse_pos"] < ekf["rmse_pos"]
    else:
        assert ekf["nees_in_bounds"] >= 0.85
        assert ekf["rmse_pos"] == oracle["rmse_pos"]


def test_cli_run_writes_results_and_prints_summary(tmp_path, small_yaml):
    result = runner.invoke(
        app, ["run", str(small_yaml), "--runs", "2", "--out", str(tmp_path / "o")]
    )
    assert result.exit_code == 0, result.output
    assert "anfekf" in result.output and "RMSE" in result.output
    assert (tmp_path / "o" / "small" / "manifest.json").is_file()
    manifest = json.loads((tmp_path / "o" / "small" / "manifest.json").read_text())
    assert manifest["runs"] == 2


def test_cli_runs_every_scenario_in_a_folder(tmp_path):
    folder = tmp_path / "scen"
    folder.mkdir()
    write_scenario(folder / "a.yaml", small_scenario(name="a", runs=1))
    write_scenario(folder / "b.yaml", small_scenario(name="b", runs=1))
    result = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "o" / "a" / "manifest.json").is_file()
    assert (tmp_path / "o" / "b" / "manifest.json").is_file()


def _bad(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(text, encoding="utf-8")
    return path


BAD_SCENARIOS = {
    "yaml-syntax": ("name: x\nruns: [1, 2\n", "YAML syntax error at line"),
    "unknown-key": ("name: x\nrunz: 3\n", "runz: unknown key"),
    "negative-sigma": ("name: x\ntrue_noise: {sigma_range: -0.1}\n", "true_noise.sigma_range"),
    "runs-zero": ("name: x\nruns: 0\n", "runs: Input should be greater than or equal to 1"),
    "missing-map": ("name: x\nworld: {landmarks: nowhere.csv}\n", "world.landmarks: map file not"),
}


@pytest.mark.parametrize("text, expected", BAD_SCENARIOS.values(), ids=BAD_SCENARIOS.keys())
def test_bad_scenarios_give_one_clean_line(tmp_path, text, expected):
    path = _bad(tmp_path, text)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    out = result.stderr.strip()
    assert out.startswith("error: ") and str(path) in out and expected in out, out
    assert len(out.splitlines()) == 1
    assert "Traceback" not in result.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "flag, value",
    [("--runs", "0"), ("--jobs", "0"), ("--seed", "-1")],
    ids=["runs", "jobs", "seed"],
)
def test_bad_flags_give_one_clean_line(tmp_path, small_yaml, flag, value):
    result = runner.invoke(app, ["run", str(small_yaml), flag, value, "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    out = result.stderr.strip()
    assert out.startswith(f"error: {flag}: must be an integer >=") and len(out.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_result_files_get_ordinary_permissions(tmp_path):
    """mkstemp makes 0600 files; results must be readable like any file the user writes."""
    _, target = _execute(tmp_path, "perm", runs=1)
    umask = os.umask(0)
    os.umask(umask)
    for name in ("steps.parquet", "summary.json", "manifest.json"):
        assert stat.S_IMODE((target / name).stat().st_mode) == 0o666 & ~umask


def test_truth_follows_the_motion_model():
    """simulate_truth's scalar loop (kept for speed) is eq. 17, i.e. models.f."""
    _, world = load_scenario(CONFIGS / "correct.yaml")
    truth = simulate_truth(world)
    for k in range(0, len(truth.u), 97):
        np.testing.assert_allclose(
            truth.x[k + 1], f(truth.x[k], truth.u[k], world.T, world.B), rtol=0, atol=1e-12
        )


def test_tables_do_not_depend_on_the_order_runs_finish():
    scenario = parse_scenario(small_scenario(runs=3))
    world = resolve_world(scenario.world, Path("x.yaml"))
    results = [simulated_run(scenario, world, i, s) for i, s in enumerate(run_seeds(scenario))]
    names = [f.name for f in scenario.filters]
    shuffled = [results[2], results[0], results[1]]
    pd.testing.assert_frame_equal(
        steps_frame("s", names, results), steps_frame("s", names, shuffled), check_exact=True
    )
    assert update_statistics(results, names) == update_statistics(shuffled, names)


def test_the_steps_table_built_on_threads_is_the_one_built_on_one(monkeypatch):
    """steps_frame builds its columns on `jobs` threads (a large table): the same table."""
    from anfekf_bench.analysis import tables

    scenario = parse_scenario(small_scenario(runs=3))
    world = resolve_world(scenario.world, Path("x.yaml"))
    results = [simulated_run(scenario, world, i, s) for i, s in enumerate(run_seeds(scenario))]
    names = [f.name for f in scenario.filters]
    one = steps_frame("s", names, results)
    monkeypatch.setattr(tables, "_THREADED_CELLS", 0)  # this small table on threads too
    pd.testing.assert_frame_equal(steps_frame("s", names, results, jobs=2), one, check_exact=True)


def run_seeds(scenario):
    return np.random.SeedSequence(scenario.seed).spawn(scenario.runs)


def test_scans_from_the_world_geometry_are_the_bytes_of_per_scan_observations():
    """The scan geometry computed once per world (SPEC 11) gives the data observe() gives."""
    from anfekf_bench.sources.simulator import observe, scan_geometry, simulate_run, world_path

    scenario, world = load_scenario(Path(__file__).parents[1] / "configs" / "wrong_r.yaml")
    path = world_path(world)
    assert np.array_equal(path.geometry.steps, [s for s in range(8, len(path.truth.u) + 1, 8)])
    sigmas = scenario.true_noise.radians()
    data = simulate_run(world, path.truth, sigmas, np.random.default_rng(5), path.geometry)
    again = simulate_run(world, path.truth, sigmas, np.random.default_rng(5))
    rng = np.random.default_rng(5)
    rng.standard_normal((len(path.truth.u), 2))  # the odometry draws come first
    noise = rng.standard_normal((len(path.geometry.steps), len(world.landmarks), 2))
    noise *= np.array(sigmas[2:])
    for i, (scan, other) in enumerate(zip(data.scans, again.scans, strict=True)):
        reference = observe(world, path.truth.x[scan.step], noise[i], scan.step)
        assert np.array_equal(scan.ids, reference.ids) and np.array_equal(other.ids, scan.ids)
        assert scan.z.tobytes() == reference.z.tobytes() == other.z.tobytes()
    assert scan_geometry(world, path.truth).range.tobytes() == path.geometry.range.tobytes()


def _truncated(result: dict, m: int) -> dict:
    """The run cut to its first m recorded steps (runs of a recorded log differ in length)."""
    cut = {k: (v[:m] if k in ("step", "t", "x_true") else v) for k, v in result.items()}
    cut["filters"] = {
        name: {k: (v[:m] if isinstance(v, np.ndarray) else v) for k, v in tr.items()}
        for name, tr in result["filters"].items()
    }
    return cut


def test_steps_table_rows_are_each_filters_trace_of_each_run():
    """Row by row against the traces it is built from (the table is built column-wise), with
    runs of different lengths and one diverged trace."""
    scenario = parse_scenario(small_scenario(runs=3))
    world = resolve_world(scenario.world, Path("x.yaml"))
    results = [simulated_run(scenario, world, i, s) for i, s in enumerate(run_seeds(scenario))]
    results[1] = _truncated(results[1], len(results[1]["step"]) // 3)
    names = [f.name for f in scenario.filters]
    results[2]["filters"][names[1]]["diverged"] = True
    steps = steps_frame("s", names, [results[1], results[2], results[0]])
    assert list(steps.columns) == STEP_COLUMNS
    assert list(steps["filter"].cat.categories) == names and set(steps["scenario"]) == {"s"}
    assert len(steps) == len(names) * sum(len(r["step"]) for r in results)
    start = 0
    for name, res in ((name, res) for name in names for res in results):
        n = len(res["step"])
        block = steps.iloc[start : start + n]
        start += n
        tr = res["filters"][name]
        assert (block["filter"] == name).all() and (block["run"] == res["run"]).all()
        np.testing.assert_array_equal(block["step"], res["step"])
        np.testing.assert_array_equal(block[["x_true", "y_true", "phi_true"]], res["x_true"])
        np.testing.assert_array_equal(block[["x_est", "y_est", "phi_est"]], tr["x"])
        np.testing.assert_array_equal(block["P_xphi"], tr["P"][:, 0, 2])
        np.testing.assert_array_equal(block["P_yy"], tr["P"][:, 1, 1])
        np.testing.assert_array_equal(block["nees"], tr["nees"])
        np.testing.assert_array_equal(block[["Q_vv", "Q_gg"]], tr["Q_diag"])
        assert (block["diverged"] == tr["diverged"]).all()
    assert steps["diverged"].sum() == len(results[2]["step"])


def test_parquet_dictionary_encodes_names_and_counters_not_measured_floats(tmp_path):
    import pyarrow.parquet as pq

    df = pd.DataFrame(
        {
            "filter": pd.Categorical(["ekf"] * 50),
            "run": np.arange(50, dtype=np.int32),
            "x": np.linspace(0.0, 1.0, 50),
        }
    )
    write_parquet(tmp_path / "x.parquet", df)
    group = pq.ParquetFile(tmp_path / "x.parquet").metadata.row_group(0)
    encodings = {group.column(i).path_in_schema: group.column(i).encodings for i in range(3)}
    assert any("DICT" in e for e in encodings["filter"])
    assert any("DICT" in e for e in encodings["run"])
    assert not any("DICT" in e for e in encodings["x"])
    pd.testing.assert_frame_equal(read_parquet(tmp_path / "x.parquet"), df)


def test_a_finished_batch_flushes_every_staged_file_before_the_first_rename(tmp_path, monkeypatch):
    """The staged tables and manifest are written without a flush each, then flushed together
    (storage.sync_files) before any of them replaces the result: a power cut cannot leave the
    manifest in place over tables that never reached the disk."""
    from .conftest import tiny_scenario

    path = write_scenario(tmp_path / "t.yaml", {"name": "t", **tiny_scenario()})
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
        return real_fsync(fd)

    def replace(src, dst, **kw):
        events.append(("replace", str(dst)))
        return real_replace(src, dst, **kw)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), tmp_path / "out")
    installed = [i for i, (kind, dst) in enumerate(events)
                 if kind == "replace" and Path(dst).parent == target]  # fmt: skip
    files = sorted(p.name for p in target.iterdir() if p.name != LOCK_FILE)
    assert MANIFEST_FILE in files and STEPS_FILE in files
    flushed = [name for kind, name in events[: installed[0]] if kind == "fsync"]
    assert sorted(set(flushed) & set(files)) == files, "every file flushed before installing"
    assert events[installed[-1]][1] == str(target / MANIFEST_FILE), "the manifest goes last"


def test_run_files_skip_the_disk_flush_result_files_do_not(tmp_path, monkeypatch):
    """A run file torn by a power cut fails its checksum and is redone; results must last."""
    import os

    from anfekf_bench.storage import read_run_file, write_json, write_run_file

    flushed = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: flushed.append(fd) or real_fsync(fd))
    result = {"run": 3, "x": np.arange(4.0)}
    write_run_file(tmp_path / "run-000003.npz", result, "fp")
    assert flushed == []
    back = read_run_file(tmp_path / "run-000003.npz", "fp")
    np.testing.assert_array_equal(back["x"], result["x"])
    write_json(tmp_path / "a.json", {"a": 1})
    write_parquet(tmp_path / "a.parquet", pd.DataFrame({"a": [1.0]}))
    assert len(flushed) == 2


def test_worker_processes_import_no_table_libraries():
    """A worker imports the runner and the fast engine only: pandas and pyarrow (a quarter of
    its start) are for the parent, which writes the tables."""
    import subprocess
    import sys

    code = (
        "import sys, anfekf_bench.runner, anfekf_bench.engines.fast;"
        "print(sorted(m for m in ('pandas', 'pyarrow', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_simulated_run_imports_neither_problems_nor_recorded_sources():
    """`anfekf run` of a robot's simulated scenario loads what it runs: the modules its command
    imports (the scenario files read, the plan, the batch, the comparisons printed through the
    result loader) leave out the problems' pipeline and the recorded logs' readers, fits and
    audit (about 0.2 s of imports, issue 37)."""
    import subprocess
    import sys

    code = (
        "import sys, anfekf_bench.cli, anfekf_bench.arguments, anfekf_bench.experiment,"
        " anfekf_bench.scenarios, anfekf_bench.sweeps, anfekf_bench.report.results;"
        "print(sorted(m for m in sys.modules if m.startswith(('anfekf_bench.problems',"
        " 'anfekf_bench.real_experiment', 'anfekf_bench.drive_audit',"
        " 'anfekf_bench.sources.recorded', 'anfekf_bench.sources.mrclam'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("umask", [0o077, 0o002])
def test_new_files_follow_the_umask_of_the_moment(tmp_path, umask):
    """The mode comes from the umask when the file is made, not when the package was imported
    (a program may change its umask after importing us)."""
    from anfekf_bench.storage import write_atomic, write_new

    before = os.umask(umask)
    try:
        write_atomic(tmp_path / "a.json", lambda tmp: tmp.write_text("{}"))
        write_new(tmp_path / "b.txt", b"text")
    finally:
        os.umask(before)
    for name in ("a.json", "b.txt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.txt"]  # no temporary left
