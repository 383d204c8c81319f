"""What each figure of `anfekf bench`'s JSON means, and the targets some of them are held to: the
file explains itself, and the README's generated bench text reads the same words."""

from __future__ import annotations

# figure: (comparison, limit, unit) on the 2-core machine (issue 6)
TARGETS: dict[str, tuple[str, float, str]] = {
    "overhead_ratio": ("<=", 1.15, "x"),
    "speedup_2_workers": (">=", 1.8, "x"),
    "anfekf_over_ekf_step_cost": ("<=", 1.5, "x"),
    "steps_parquet_mb": ("<=", 50.0, "MiB"),
    "peak_rss_mb": ("<=", 2048.0, "MiB"),
    # issue 14
    "fast_step_ratio_ekf": ("<=", 0.01, "x"),
    "fast_step_ratio_anfekf": ("<=", 0.01, "x"),
    "fast_step_ratio_max": ("<=", 0.01, "x"),  # issue 22: every built-in kind
    "fast_e2e_scenario_s": ("<=", 2.0, "s"),
    "fast_sweep_batch_s": ("<=", 30.0, "s"),
    "fast_summary_max_rel_diff": ("<=", 1e-9, ""),
    # issue 37: the paper scenarios end to end (breakdown.py)
    "fast_e2e_paper_total_s": ("<=", 5.0, "s"),
    "fast_e2e_over_filter": ("<=", 3.0, "x"),
    "make_zoo_s": ("<=", 40.0, "s"),
    "first_run_compiled": ("<=", 0, "functions"),
    "default_over_ekf_fast_step_cost": ("<=", 30.0, "x"),  # issue 36
}


# What each figure of the JSON is, written into it so the file explains itself.
DEFINITIONS = {
    "ekf_bare_step_us": "median time per control step of a plain filterpy ExtendedKalmanFilter"
    " loop (predict every step, one update per landmark seen; no gate, checks or recording)",
    "ekf_harness_step_us": "the same EKF (RobotEKF) through runner.run_filter plus the per-run"
    " metrics of runner.run_one (pose errors, NEES); simulation excluded from both",
    "overhead_ratio": "median over repeats of harness / bare time, timed back to back",
    "anfekf_step_us": "ANFEKF (adapt R) through the harness on the same data",
    "anfekf_over_ekf_step_cost": "median over repeats of ANFEKF / EKF harness time",
    "speedup_2_workers": "median over repeats of the 1-worker / 2-worker batch wall time"
    " (joblib loky pool warmed first)",
    "peak_rss_mb": "largest over the scenarios of: peak RSS (VmHWM) of the main process plus"
    " that of each child (workers, resource trackers); an upper bound on memory held at once",
    "steps_parquet_mb": "largest steps.parquet over the scenarios (MiB)",
    "wall_time_paper_scenarios_s": "experiment.execute wall time of each scenario file in a"
    " fresh process (worker start-up included), and their sum",
    "engine_step_us": "per filter kind: median time per control step of filterpy_engine.run_filter"
    " and of fast.run_filter_fast (engine calls only: filters and contexts built outside, no"
    " metrics; the run's scans flattened beforehand, as a run's filters share that) and the"
    " median over repeats of their paired ratio fast / filterpy; ratio_with_prep charges the"
    " run's whole flattening (fast_prep_step_us) to this one filter",
    "fast_step_ratio_ekf": "engine_step_us ratio fast / filterpy of the EKF",
    "fast_step_ratio_anfekf": "the largest engine_step_us ratio fast / filterpy of the ANFEKF"
    " adapting R, Q and RQ",
    "fast_step_ratio_max": "the largest engine_step_us ratio fast / filterpy over every kind"
    " timed (engine_step_us names them)",
    "fast_prep_step_us": "the fast engine's flattening of a run's scans into arrays (once per"
    " run, shared by its filters), per control step",
    "fast_jit": "whether the fast engine's kernels are numba-compiled (false: plain Python)",
    "fast_warm_up_s": "this process's first fast-engine calls: numba compiling the kernels, or"
    " loading them from its on-disk cache",
    "fast_compile_s": "numba compiling every kernel from an empty cache, in a fresh interpreter"
    " (import excluded); null at quick sizes or without numba",
    "fast_cache_load_s": "the same kernels loaded from numba's on-disk cache in a fresh"
    " interpreter (import excluded)",
    "fast_compiled_signatures": "the compiled signatures that compile wrote to numba's cache"
    " (every jitted function, callees included, once per signature)",
    "fast_compiled_twice": "the functions it compiled for more than one signature (a constant"
    " argument typed as a literal compiles its callee again): none expected",
    "fast_engine_max_abs_diff": "largest |fast - filterpy| of x, P, R_diag, Q_diag over the timed"
    " run and filter kinds (the same update, rejection and divergence counts are required)",
    "fast_e2e_scenario_s": "experiment.execute wall time of the step scenario file's runs on the"
    " fast engine, 2 workers, kernels warmed in this process and the workers (compile"
    " excluded); simulation, filters, metrics and Parquet included",
    "fast_e2e_cli_s": "median wall time of the whole command `anfekf run <step scenario> --engine"
    " fast --jobs 2` in a fresh process: interpreter start, imports, worker start, kernels loaded"
    " from numba's on-disk cache (compile excluded), tables printed; null at quick sizes",
    "fast_summary_max_rel_diff": "largest relative difference of a summary figure of that run from"
    " the filterpy run of the same file (the scenario probe)",
    "default_over_ekf_fast_step_cost": "per-step time of the default filter (a kind whose spec"
    " says `default_filter`, with its defaults: vb-imm, 9 members) over the EKF's, both on the"
    " fast engine (engine_step_us)",
    "fast_e2e_paper_total_s": "the paper's four scenario files on the fast engine end to end"
    " (`experiment.execute` in this process, caches warm, process start excluded), each the"
    " median of its breakdown.E2E_REPEATS walls (fast_e2e_breakdown's e2e_walls_s), summed",
    "fast_e2e_over_filter": "the largest over the paper scenarios of that median end-to-end wall"
    " over the filters' own time (the breakdown's filter phase: every filter instance on every"
    " run, one after the other in this process)",
    "report_paper_total_s": "the report of each paper scenario's fast-engine result (figures and"
    " HTML included), in this process, summed (the breakdown's report phases)",
    "make_zoo_s": "`make zoo` as it runs: `anfekf run configs/zoo` then `anfekf report` on it,"
    " each a fresh process with numba's cache warm, wall time summed (make_zoo has each);"
    " null at quick sizes",
    "first_run_compiled": "functions numba compiled on the first `anfekf run --engine fast"
    " --runs 2` of the paper's scenarios and of configs/zoo, in fresh processes whose numba"
    " cache holds only what the warm-up (`make setup`) compiled (first_run names them);"
    " null at quick sizes",
    "fast_sweep_batch_s": "wall time of a sweep-sized batch on the fast engine: cells x runs x 5"
    " filters (1500 filter-runs at full size), each cell an experiment.execute with summaries"
    " only (steps_table false), 2 workers kept warm across cells",
}
