"""Shared fixtures: a short route on a small map, so end-to-end tests take seconds."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

os.environ.setdefault("MPLBACKEND", "Agg")

SMALL_WORLD = {
    "landmarks": [[10, 8], [25, -6], [40, 10], [55, -5], [30, 15], [15, -10], [48, 4]],
    "waypoints": [[20, 0], [40, 8], [55, 0]],
}


def small_scenario(**overrides) -> dict:
    """A scenario dict on SMALL_WORLD (a ~60 m route: ~800 control steps)."""
    doc = {
        "name": "small",
        "seed": 7,
        "runs": 4,
        "jobs": 1,
        "record_every": 1,
        "world": dict(SMALL_WORLD),
        "filter_noise": {"sigma_range": 2.0, "sigma_bearing_deg": 0.1},
        "filters": [
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ],
    }
    doc.update(overrides)
    return doc


def tiny_scenario(**overrides) -> dict:
    """One run on a two-landmark map, the EKF alone: a batch takes a fraction of a second."""
    doc = {
        "seed": 3,
        "runs": 1,
        "jobs": 1,
        "record_every": 8,
        "world": {"landmarks": [[5, 3], [10, -2]], "waypoints": [[8, 0]]},
        "filters": [{"name": "ekf", "kind": "ekf"}],
    }
    doc.update(overrides)
    return doc


def write_scenario(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


@pytest.fixture
def small_yaml(tmp_path: Path) -> Path:
    return write_scenario(tmp_path / "small.yaml", small_scenario())


def live_group_members(pgid: int) -> list[int]:
    """Processes of a process group that are still running (zombies are not): what a killed
    command leaves behind."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            alive.append(int(stat.parent.name))
    return alive


# The fast tier, `pytest -m "not slow"`: these end-to-end tests (each several seconds on the
# 2-core machine: whole scenarios, worker pools, killed processes, a Dask cluster) are marked
# slow here, by module and test function (every parameter), besides those marked in their own
# files. `make test` runs everything. Measured with `pytest --durations` (docs/getting-started.md).
SLOW_TESTS: dict[str, set[str]] = {
    "test_api": {"test_a_run_from_python_reads_back"},
    "test_api_problems": {"test_a_linear_problem_runs_from_python_as_from_the_command_line"},
    "test_augmented": {"test_augmented_families_fast_equal_filterpy"},
    "test_bench": {
        "test_quick_bench_writes_every_figure",
        "test_the_command_line_probe_runs_anfekf_run_in_a_fresh_process",
        "test_warmed_workers_are_the_ones_a_batch_uses",
    },
    "test_cli_init": {"test_fast_without_numba_says_so_once_and_the_manifest_records_it"},
    "test_cli_ux": {
        "test_check_piped_into_head_keeps_its_verdict",
        "test_folder_run_checks_every_output_folder_before_running_any",
        "test_other_commands_piped_into_head_stop_quietly",
        "test_shell_completion_completes_commands_and_options",
        "test_skip_existing_runs_the_others",
    },
    "test_confinement": {
        "test_nothing_outside_the_scenario_folder_ever_changes",
        "test_planted_run_files_are_refused_never_executed",
        "test_what_a_killed_first_attempt_leaves_is_taken_over",
    },
    "test_custom_filter": {"test_the_worked_example_runs_through_the_extension_point"},
    "test_dask": {
        "test_cluster_lost_mid_batch_is_reported",
        "test_dask_batch_reports_each_run_and_skips_done_ones",
        "test_dask_run_equals_local_run",
        "test_scheduler_without_workers_is_reported",
        "test_unreachable_scheduler_is_one_line_within_timeout",
    },
    "test_drives": {"test_regenerate_refuses_a_changed_original"},
    "test_ekf_ml_real": {
        "test_ekf_ml_recovers_the_true_sigmas_of_a_synthetic_drive",
        "test_objective_equals_the_robot_ekf_summed_nll",
        "test_the_objective_does_not_depend_on_units_and_the_accepted_only_sum_does",
    },
    "test_fast_adaptive": {"test_paper_scenarios"},
    "test_fast_engine": {
        "test_paper_scenario",
        "test_runs_without_numba",
    },
    "test_fast_primitives": {
        "test_inv_is_numpys_with_pivoting",
        "test_inv_raises_as_numba_does",
        "test_lstsq_full_rank_is_numpys",
        "test_products_are_numpys",
        "test_products_sum_in_k_order",
    },
    "test_filter_bank": {"test_bicycle_bank_is_used_by_the_registry"},
    "test_filter_vb_bank": {
        "test_grid_rule_is_the_imm_on_the_same_grid",
        "test_weight_goes_to_the_true_qu",
    },
    "test_fitted": {
        "test_manifest_records_the_fit_and_resume_reuses_it",
        "test_two_noise_fits_run_their_starts_in_one_batch_with_the_same_fits",
    },
    "test_fitting": {"test_each_declared_fit_goes_through_the_one_entry_point"},
    "test_hardening": {
        "test_any_document_loads_or_fails_cleanly",
        "test_cli_error_line_equals_loader_error",
        "test_cli_table_shows_the_diverged_count",
        "test_diverged_run_is_counted_and_kept_out_of_the_means",
        "test_real_process_prints_one_line",
    },
    "test_hardening3": {
        "test_a_description_with_a_script_link_is_plain_text_in_report_html",
        "test_a_file_of_another_batch_is_refused",
        "test_a_recorded_log_whose_odometry_misses_the_truth_keeps_the_previous_result",
        "test_a_sweep_without_the_oracle_is_reported",
        "test_ctrl_c_in_the_first_second_is_one_line",
        "test_kill_9_during_a_forced_rerun_keeps_the_previous_result",
    },
    "test_hardening4_api": {"test_report_takes_one_path_as_one_result"},
    "test_hardening4_check": {
        "test_a_full_stdout_is_one_line_and_a_nonzero_exit",
        "test_an_empty_numba_cache_is_seen_as_cold",
        "test_kinds_imports_no_compiler_nor_plots",
        "test_the_one_worker_cluster_has_its_worker_before_a_test_starts",
    },
    "test_hardening4_inputs": {"test_any_file_name_gives_a_valid_starter_or_one_line"},
    "test_interrupt": {
        "test_complete_folder_refuses_then_force_overwrites",
        "test_ctrl_c_in_process_then_resume",
        "test_folder_killed_while_swapping_in_the_result_is_recomputed",
        "test_killed_run_leaves_nothing_complete_and_resumes",
        "test_torn_run_file_and_stray_temporaries_are_redone",
    },
    "test_kalmannet": {
        "test_a_resumed_batch_reads_the_trained_weights_from_the_cache",
        "test_a_tiny_robot_training_runs_an_evaluation_run_with_finite_estimates",
        "test_anfekf_run_trains_kalmannet_and_records_the_weights_and_time",
        "test_held_out_runs_keep_the_epoch_that_does_best_on_them",
        "test_on_a_linear_gaussian_model_its_mse_is_within_10_percent_of_the_kalman_filter",
        "test_same_seed_same_weights_bytes_and_another_seed_others",
    },
    "test_kalmannet_real": {
        "test_each_fold_trains_on_the_other_datasets_drive_only_and_deterministically",
        "test_on_protocol_segments_it_trains_on_the_training_segments_only",
    },
    "test_mrclam": {"test_conversion_reproduces_the_shipped_tables"},
    "test_pipeline": {
        "test_a_simulated_run_imports_neither_problems_nor_recorded_sources",
        "test_cli_runs_every_scenario_in_a_folder",
        "test_ekf_consistency_acceptance",
        "test_output_files_and_columns",
        "test_results_do_not_depend_on_worker_count",
        "test_small_batch_runs_in_process",
        "test_steps_table_rows_are_each_filters_trace_of_each_run",
        "test_tables_do_not_depend_on_the_order_runs_finish",
        "test_worker_processes_import_no_table_libraries",
    },
    "test_problems_custom": {"test_the_example_runs_through_the_command_line"},
    "test_problems_fast": {"test_the_compiled_loop_equals_the_python_filter"},
    "test_readme": {"test_the_json_schemas_accept_every_shipped_scenario"},
    "test_real_data": {
        "test_a_users_log_runs_end_to_end",
        "test_an_interrupted_real_batch_resumes_from_its_saved_segments",
    },
    "test_registry_capabilities": {
        "test_the_noise_figure_has_a_line_for_every_adaptive_filter_and_none_for_fixed_ones",
    },
    "test_report": {
        "test_dpi_sets_the_figure_resolution",
        "test_other_formats_are_valid_files",
        "test_the_html_report_is_written_again_byte_for_byte",
    },
    "test_report_many": {
        "test_the_leaderboard_has_no_overlapping_labels",
        "test_the_overview_has_no_overlapping_labels",
    },
    "test_starts": {
        "test_a_scenario_with_starts_runs_reports_and_compares_with_the_start_at_one",
        "test_the_oracle_is_told_the_truth_whatever_the_starts",
    },
    "test_statistics": {"test_coverage_with_a_known_truth"},
    "test_sweeps": {
        "test_an_interrupted_sweep_resumes_to_the_same_table",
        "test_cells_are_ordered_naturally_and_equal_the_scenario_written_by_hand",
        "test_the_sweep_report_draws_lines_or_heatmaps",
    },
    "test_zoo": {"test_R_and_Qu_stay_positive_and_within_bounds"},
}


# Whole modules left to the full suite: each family's engine equivalence in every mode, pure
# Python and forced divergence. The quick tier keeps tests/test_engines_equivalence.py, which
# checks every registered kind on both engines and both motion models.
SLOW_MODULES = {
    "test_fast_adaptive", "test_fast_adaptive_cm", "test_fast_bank", "test_fast_als",
    # one module-scoped report of real scenarios that most of their tests read
    "test_report", "test_report_mixed", "test_check_sweeps",
}  # fmt: skip


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1] if item.module else ""
        heavy = item.get_closest_marker("heavy") is not None  # the longest: slow as well
        if heavy or module in SLOW_MODULES or item.originalname in SLOW_TESTS.get(module, ()):
            item.add_marker(pytest.mark.slow)


def small_world_noise_off(seed: int, runs: int):
    """(scenario, world, runs) of the small world whose filters assume Qu about 10x too large
    and R off (sigma_range 0.5 m): every adaptive rule has something to adapt; `runs` runs
    simulated from `seed` (the fast engine's equivalence tests share it)."""
    import numpy as np

    from anfekf_bench.config import parse_scenario, resolve_world
    from anfekf_bench.runner import simulate

    doc = small_scenario(
        record_every=1, filter_noise={"sigma_v": 3.0, "sigma_gamma_deg": 9.0, "sigma_range": 0.5}
    )
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, Path("small.yaml"))
    data = [simulate(scenario, world, s) for s in np.random.SeedSequence(seed).spawn(runs)]
    return scenario, world, data


def corrupted_half_way(data, what: str):
    """(run data, the corrupted scan): `data` with, half-way through (at the middle scan that saw
    two landmarks), either an odometry sample NaN 5 steps before that scan ("odometry") or that
    scan's second range infinite ("measurement"); the engines' divergence tests share it."""
    import dataclasses

    import numpy as np

    from anfekf_bench.sources.simulator import RunData

    scans = [s for s in data.scans if len(s.ids) >= 2]
    bad = scans[len(scans) // 2]
    if what == "odometry":
        u = data.u_odo.copy()
        u[bad.step - 5, 0] = np.nan
        return RunData(truth=data.truth, u_odo=u, scans=data.scans), bad
    z = bad.z.copy()
    z[1, 0] = np.inf
    i = data.scans.index(bad)
    scans = data.scans[:i] + (dataclasses.replace(bad, z=z),) + data.scans[i + 1 :]
    return RunData(truth=data.truth, u_odo=data.u_odo, scans=scans), bad


WORKER_START_S = 180  # how long a Dask worker process may take to start and register


@contextlib.contextmanager
def cluster_with_one_worker() -> Iterator[tuple[str, subprocess.Popen]]:
    """A Dask LocalCluster with no workers of its own and one worker process without a nanny
    (one thread): killing that process leaves the cluster with no worker at all, as nothing
    restarts it. Yields (scheduler address, the worker's process)."""
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        n_workers=0, processes=True, host="127.0.0.1", dashboard_address=None
    )
    worker = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", cluster.scheduler_address,
         "--no-nanny", "--nthreads", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        # The worker's process imports distributed first (seconds on a loaded 2-core machine):
        # a test that gave it 2 s to register failed under load. Wait for it here, generously.
        deadline = time.monotonic() + WORKER_START_S
        while not cluster.scheduler.workers:
            if worker.poll() is not None:
                pytest.fail(
                    f"the Dask worker process ended (exit {worker.returncode}) unregistered"
                )
            if time.monotonic() > deadline:
                pytest.fail(f"no Dask worker registered within {WORKER_START_S} s")
            time.sleep(0.05)
        yield cluster.scheduler_address, worker
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait()
        cluster.close()
