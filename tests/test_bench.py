"""`anfekf bench`: the machinery at tiny sizes. No timing thresholds: timings here are noise."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from statistics import median

import numpy as np
import pytest
from typer.testing import CliRunner

from anfekf_bench import bench
from anfekf_bench import breakdown as breakdown_module
from anfekf_bench.cli import app
from anfekf_bench.config import parse_scenario, resolve_world

from .conftest import small_scenario, write_scenario

runner = CliRunner()

# Figures the issue names; each must be a finite positive number.
NUMBER_KEYS = [
    "overhead_ratio",
    "ekf_bare_step_us",
    "ekf_harness_step_us",
    "anfekf_step_us",
    "anfekf_over_ekf_step_cost",
    "speedup_2_workers",
    "batch_1_worker_s",
    "batch_2_workers_s",
    "peak_rss_mb",
    "steps_parquet_mb",
    "fast_step_ratio_ekf",
    "fast_step_ratio_anfekf",
    "fast_prep_step_us",
    "fast_warm_up_s",
    "fast_e2e_scenario_s",
    "fast_sweep_batch_s",
]


def _small_configs(folder: Path) -> Path:
    """The two scenario files the bench needs, on the small world, 2 runs each.

    jobs 1 spares each scenario's subprocess a worker pool (seconds of imports); the bench's own
    1-vs-2-worker batch still starts one.
    """
    folder.mkdir()
    for name in ("correct", "wrong_r"):
        doc = small_scenario(name=name, runs=2, jobs=1, record_every=8)
        if name == "correct":
            doc.pop("filter_noise")
        write_scenario(folder / f"{name}.yaml", doc)
    return folder


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_bare_filterpy_loop_is_the_same_filter_as_the_harness_ekf():
    """With the true noise and no gate both fuse every measurement: same estimate, to round-off.

    (The harness also symmetrises P after each update; that is the only difference.)
    """
    scenario = parse_scenario(small_scenario(gate_probability=None, filter_noise={}))
    world = resolve_world(scenario.world, Path("small.yaml"))
    setup = bench.step_setup(scenario, world)
    bare, ekf = setup.bare(), setup.ekf()
    bench.bare_ekf_loop(bare, setup.data, world, setup.bare_Qu())
    trace = bench.harness_pass(ekf, setup.data, world, scenario.record_every, setup.x_true)
    assert ekf.n_updates == sum(len(s.ids) for s in setup.data.scans) > 10
    assert not trace["diverged"]
    np.testing.assert_allclose(bare.x, ekf.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(bare.P, ekf.P, rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(trace["x"][-1], ekf.x)  # record_every 1: last step recorded


def test_quick_bench_writes_every_figure(tmp_path):
    configs = _small_configs(tmp_path / "configs")
    out = tmp_path / "deep" / "bench.json"
    result = runner.invoke(app, ["bench", "--quick", "--configs", str(configs), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "overhead_ratio" in result.output and "speedup_2_workers" in result.output
    doc = json.loads(out.read_text())
    assert doc["quick"] is True
    bad = {k: doc.get(k) for k in NUMBER_KEYS if not _finite_positive(doc.get(k))}
    assert not bad, f"not finite positive numbers: {bad}"
    walls = doc["wall_time_paper_scenarios_s"]
    assert set(walls) == {"correct", "wrong_r", "total"}
    assert all(_finite_positive(v) for v in walls.values())
    assert walls["total"] == pytest.approx(walls["correct"] + walls["wrong_r"])
    for name, figures in doc["scenarios"].items():
        assert figures["runs"] == 2, name
        assert figures["peak_rss_mb"] >= figures["peak_rss_main_mb"] > 0
    assert set(doc["targets"]) == set(bench.TARGETS)
    for key, target in doc["targets"].items():
        assert target["value"] == doc[key] and isinstance(target["met"], bool)
    assert doc["updates"]["ekf"]["fused"] > 0
    assert doc["machine"]["cores"] >= 1 and doc["machine"]["cpu_model"]
    assert doc["versions"]["filterpy"] != "not installed"
    assert len(doc["raw_seconds"]["step_pass"]["bare"]) == bench.QUICK.repeats
    # the fast engine against filterpy: every kind on both, same data, same counts
    assert set(doc["engine_step_us"]) == set(bench.ENGINE_KINDS)
    for kind, figures in doc["engine_step_us"].items():
        keys = ("filterpy", "fast", "ratio", "ratio_with_prep")
        assert all(_finite_positive(figures[k]) for k in keys), kind
        assert figures["ratio_with_prep"] > figures["fast"] / figures["filterpy"]
        assert len(doc["raw_seconds"]["engine_pass"][kind]["fast"]) == bench.QUICK.repeats
    assert doc["engine_updates"]["ekf"] == doc["updates"]["ekf"]
    assert doc["fast_engine_max_abs_diff"] < 1e-9
    assert doc["fast_summary_max_rel_diff"] < 1e-9  # summaries of both engines, same runs
    assert doc["fast_compile_s"] is None  # a fresh-interpreter compile: full sizes only
    assert doc["fast_e2e_cli_s"] is None and doc["fast_e2e"]["cli_wall_s"] == []  # full only
    assert doc["fast_e2e"]["runs"] == 2 and doc["fast_e2e"]["sweep"]["filter_runs"] == 20
    assert "step_us anfekf_RQ: fast" in result.output and "fast_sweep_batch_s" in result.output
    # issue 37: the end-to-end breakdown of every paper scenario on the fast engine
    breakdown = doc["fast_e2e_breakdown"]
    assert set(breakdown["scenarios"]) == {"correct", "wrong_r"}
    for name, b in breakdown["scenarios"].items():
        assert b["runs"] == 2 and b["placement"] == "in-process", name
        assert set(b["phases_s"]) == {
            "simulate", "filter", "metrics", "store", "tables", "report"
        }  # fmt: skip
        assert all(_finite_positive(v) for v in b["phases_s"].values()), name
        assert b["e2e_over_filter"] == pytest.approx(b["e2e_s"] / b["phases_s"]["filter"])
        walls = b["e2e_walls_s"]  # the end-to-end figure is the median of its repeats
        assert len(walls) == breakdown_module.E2E_REPEATS and b["e2e_s"] == median(walls)
    assert breakdown["e2e_total_s"] == pytest.approx(
        sum(b["e2e_s"] for b in breakdown["scenarios"].values())
    )
    assert "e2e / filter correct" in result.output
    assert doc["report_paper_total_s"] == pytest.approx(
        sum(b["phases_s"]["report"] for b in breakdown["scenarios"].values())
    )
    # make zoo and the first run after the warm-up: fresh processes, full sizes only
    assert doc["make_zoo_s"] is None and doc["first_run_compiled"] is None


def test_the_command_line_probe_runs_anfekf_run_in_a_fresh_process(tmp_path):
    path = write_scenario(tmp_path / "tiny.yaml", small_scenario(name="tiny", runs=2))
    walls = bench.time_cli_runs(path, tmp_path / "out", 1)
    assert len(walls) == 1 and _finite_positive(walls[0])
    manifest = json.loads((tmp_path / "out" / "tiny" / "manifest.json").read_text())
    assert manifest["engine"] == "fast" and manifest["jobs"] == 2
    (tmp_path / "bad.yaml").write_text("name: [\n")
    with pytest.raises(bench.BenchError, match="bad.yaml: anfekf run failed"):
        bench.time_cli_runs(tmp_path / "bad.yaml", tmp_path / "out", 1)


def test_sweep_cells_are_fast_summary_only_scenarios_of_five_filters():
    base = parse_scenario(small_scenario(name="base", claims=[]))
    cells = bench.sweep_cells(base, 3, 4)
    assert [c.name for c in cells] == ["base-cell0", "base-cell1", "base-cell2"]
    for cell in cells:
        assert (cell.runs, cell.steps_table, cell.engine) == (4, False, "fast")
        assert [f.name for f in cell.filters] == [f["name"] for f in bench.SWEEP_FILTERS]
    ranges = [c.filter_noise.sigma_range for c in cells]
    assert ranges == pytest.approx([0.5, 2.0, 8.0])  # 0.25 .. 4 x the base's 2.0


def test_summary_difference():
    a = [{"filter": "ekf", "rmse_pos": 1.0, "anees": float("nan"), "runs": 3, "scenario": "s"}]
    b = [{"filter": "ekf", "rmse_pos": 1.0 + 1e-12, "anees": float("nan"), "runs": 3}]
    assert bench.summary_max_rel_diff(a, b) == pytest.approx(1e-12, rel=1e-3)
    assert bench.summary_max_rel_diff(a, [{**b[0], "anees": 1.0}]) == math.inf
    assert bench.summary_max_rel_diff(a, [{**b[0], "filter": "other"}]) == math.inf


def _no_wrong_r(tmp_path: Path) -> list[str]:
    configs = _small_configs(tmp_path / "configs")
    (configs / "wrong_r.yaml").unlink()
    return ["--configs", str(configs)]


def _out_is_folder(tmp_path: Path) -> list[str]:
    return ["--configs", str(_small_configs(tmp_path / "configs")), "--out", str(tmp_path)]


def _bad_scenario(tmp_path: Path) -> list[str]:
    configs = _small_configs(tmp_path / "configs")
    (configs / "correct.yaml").write_text("name: correct\nruns: -1\n")
    return ["--configs", str(configs)]


def _bad_other_scenario(tmp_path: Path) -> list[str]:
    """Only run end to end at the close: still refused before any timing."""
    configs = _small_configs(tmp_path / "configs")
    (configs / "zz.yaml").write_text("name: zz\nfilters: []\n")
    return ["--configs", str(configs)]


@pytest.mark.parametrize(
    ("make_args", "message"),
    [
        pytest.param(lambda p: ["--configs", str(p / "nope")], "must be a folder", id="no-configs"),
        pytest.param(_no_wrong_r, "holds no wrong_r.yaml", id="configs-without-wrong_r"),
        pytest.param(_out_is_folder, "must be a file path", id="out-is-a-folder"),
        pytest.param(_bad_scenario, "runs", id="invalid-scenario"),
        pytest.param(_bad_other_scenario, "zz.yaml: filters", id="invalid-other-scenario"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, make_args, message):
    result = runner.invoke(app, ["bench", "--quick", *make_args(tmp_path)])
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert err.startswith("error:") and message in err and len(err.splitlines()) == 1
    assert "Traceback" not in result.output


def _pid() -> int:
    import os

    return os.getpid()


def test_warmed_workers_are_the_ones_a_batch_uses():
    """Warming a different joblib pool than the batches' would leave their workers cold (the
    first timed batch would then pay for starting and loading them)."""
    from joblib import Parallel, delayed

    from anfekf_bench.workers import local_workers

    warmed = bench.warm_workers(2)
    try:
        assert len(warmed) == 2
        with local_workers():
            used = set(Parallel(n_jobs=2)(delayed(_pid)() for _ in range(8)))
        assert used <= warmed
    finally:
        bench._shutdown_workers()


def test_every_built_in_kind_is_timed_on_both_engines():
    """`anfekf bench` times every built-in kind (issue 22), `kalmannet` with a network of the
    default size and seeded random weights (no PyTorch needed); the fitted EKFs and the oracle
    are the EKF's kernel with other noise (timed as `ekf`; `ekf-aug-calibrated`: `ekf-aug`'s), a
    user's class has no fast kernel."""
    from anfekf_bench.filters.kalmannet import KalmanNetSpec
    from anfekf_bench.filters.registry import SPEC_BY_KIND

    timed = {spec.kind for spec in bench.ENGINE_KINDS.values()}
    assert timed == set(SPEC_BY_KIND) - {
        "custom",
        "ekf-oracle",
        "ekf-ml",
        "ekf-tuned",
        "ekf-aug-calibrated",
    }
    weights = bench.ENGINE_KINDS["kalmannet"].trained_weights
    assert weights.hidden_size == KalmanNetSpec.model_fields["hidden_size"].default
    again = bench.bench_kalmannet().trained_weights
    assert again.to_bytes() == weights.to_bytes()  # seeded


def test_first_run_compiles_reads_numba_cache_log(monkeypatch, tmp_path) -> None:
    """The functions numba saved to its cache on a first run are read from its cache log (the
    format of numba.core.caching's `_cache_log`), each once; index saves and loads are not
    compiles."""
    from anfekf_bench import breakdown

    log = (
        "[cache] index loaded from '/c/loop.run_loop-148.py311.nbi'\n"
        "[cache] data loaded from '/c/loop.run_loop-148.py311.1.nbc'\n"
        "[cache] data saved to '/c/simulator._truth-120.py311.1.nbc'\n"
        "[cache] index saved to '/c/simulator._truth-120.py311.nbi'\n"
    )
    calls = []

    def fake_cli(args, env=None):
        calls.append((args, env))
        return 1.5, log

    monkeypatch.setattr(breakdown, "_cli", fake_cli)
    got = breakdown.first_run_compiles(tmp_path / "cache", [Path("a"), Path("b")], tmp_path)
    assert got == {"compiled": ["simulator._truth-120.py311.1.nbc"], "count": 1, "wall_s": 3.0}
    assert all(env["NUMBA_CACHE_DIR"] == str(tmp_path / "cache") for _, env in calls)
    assert all(env["NUMBA_DEBUG_CACHE"] == "1" and "fast" in args for args, env in calls)
    monkeypatch.setattr(breakdown, "_cli", lambda args, env=None: (2.0 + len(args), ""))
    zoo = breakdown.make_zoo_wall(Path("zoo"), tmp_path)
    assert zoo["total_s"] == zoo["run_s"] + zoo["report_s"] and zoo["run_s"] > zoo["report_s"]


def test_compiled_signatures_counts_each_functions_signatures(tmp_path) -> None:
    """From numba's cache file names (NAME-LINE.pyXY.N.nbc): every signature counted, the
    functions with two or more listed; index files and other files ignored."""
    files = [
        "a/kernels.record-832.py311.1.nbc", "a/kernels.record-832.py311.2.nbc",
        "a/kernels.record-832.py311.nbi", "b/loop_fading_0a.run_loop-13.py311.1.nbc",
        "b/motion_terms.step_terms-31.py313t.1.nbc", "b/notes.txt",
        "a/fast.run-77.py311.1.nbc", "b/fast.run-77.py311.1.nbc",  # two files' functions
    ]  # fmt: skip
    for name in files:
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    got = breakdown_module.compiled_signatures(tmp_path)
    assert got == {"signatures": 6, "compiled_twice": ["a/kernels.record-832"]}
    assert breakdown_module.compiled_signatures(tmp_path / "none") == {
        "signatures": 0, "compiled_twice": [],
    }  # fmt: skip


_LITERAL_CODE = """
import numpy as np
from numba import njit

@njit(cache=True)
def scale(x, k):
    return x * k

@njit(cache=True)
def literal():
    return scale(2.0, 3)

@njit(cache=True)
def not_literal():
    return scale(2.0, np.int64(3))

assert literal() == 6.0 and not_literal() == 6.0
"""


def test_a_literal_argument_compiles_its_callee_again(tmp_path) -> None:
    """Why the kernels pass constants as np.int64(...) (docs/DESIGN.md, "Engines"): a constant
    argument is typed as a literal and compiles the callee for it besides the int64 signature,
    and `compiled_signatures` sees it."""
    pytest.importorskip("numba")
    (tmp_path / "literal_args.py").write_text(_LITERAL_CODE)
    cache = tmp_path / "cache"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(tmp_path))
    subprocess.run([sys.executable, "-c", "import literal_args"], env=env, check=True)
    got = breakdown_module.compiled_signatures(cache)
    assert [name.split("/")[-1] for name in got["compiled_twice"]] == ["literal_args.scale-5"]
    assert got["signatures"] == 4  # scale twice, literal, not_literal
