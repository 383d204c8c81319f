"""Noise that changes while the robot drives (SPEC 14): the `noise_schedule` block, the simulator's
draws under it, the oracle that follows it, and the strict validation of the block."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from anfekf_bench.config import ScenarioError, parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters.context import build_filter, filter_context
from anfekf_bench.filters.ekf import RobotEKF, ScheduledOracle
from anfekf_bench.models import wrap_angle
from anfekf_bench.runner import engine_of, run_filter_on, simulate
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.schedule import NoiseSchedule
from anfekf_bench.sources.simulator import Truth, scan_geometry, simulate_run, world_path

from .conftest import small_scenario, write_scenario

SIGMAS = (0.3, math.radians(3.0), 0.1, math.radians(1.0))


def scenario_and_world(doc: dict, tmp_path: Path | None = None):
    scenario = parse_scenario(doc)
    return scenario, resolve_world(scenario.world, Path(tmp_path or ".") / "s.yaml")


# ---------------------------------------------------------------------------------------------
# The schedule's factors, by hand


def test_step_and_ramp_factors_by_hand():
    schedule = NoiseSchedule.model_validate({
        "changes": [
            {"channels": ["range"], "factor": 9, "start_s": 10, "end_s": 20},
            {"channels": ["Qu"], "factor": 5, "start_s": 10, "end_s": 30, "shape": "ramp"},
            {"channels": ["R"], "factor": 2, "start_s": 15},
        ]
    })  # fmt: skip
    t = np.array([0.0, 9.999, 10.0, 15.0, 19.999, 20.0, 25.0, 30.0, 100.0])
    f = schedule.variance_factors(t)  # (speed, steering, range, bearing)
    np.testing.assert_allclose(f[:, 2], [1, 1, 9, 18, 18, 2, 2, 2, 2])
    np.testing.assert_allclose(f[:, 3], [1, 1, 1, 2, 2, 2, 2, 2, 2])
    # ramp from 1 at 10 s to 5 at 30 s: 1 + 4 (t - 10) / 20, held after
    ramp = [1, 1, 1, 2, 1 + 4 * 9.999 / 20, 3, 4, 5, 5]
    np.testing.assert_allclose(f[:, 0], ramp)
    np.testing.assert_allclose(f[:, 1], ramp)
    assert schedule.change_points() == [10.0, 15.0, 20.0, 30.0]
    assert schedule.change_points(t_end=25.0) == [10.0, 15.0, 20.0]


def test_true_variances_of_outliers_are_moment_matched():
    contaminated = NoiseSchedule.model_validate({
        "outliers": {"model": "contaminated", "probability": 0.1, "variance_factor": 50,
                     "channels": ["range"], "start_s": 5, "end_s": 8},
    })  # fmt: skip
    var = contaminated.true_variances(SIGMAS, np.array([1.0, 5.0, 7.9, 8.0]))
    nominal = np.square(SIGMAS)
    np.testing.assert_allclose(var[:, 2], nominal[2] * np.array([1, 0.9 + 5.0, 0.9 + 5.0, 1]))
    np.testing.assert_allclose(var[:, [0, 1, 3]], np.tile(nominal[[0, 1, 3]], (4, 1)))
    student = NoiseSchedule.model_validate({"outliers": {"model": "student_t", "dof": 4}})
    np.testing.assert_allclose(student.true_variances(SIGMAS, [0.0])[0, 2:], nominal[2:] * 2.0)


# ---------------------------------------------------------------------------------------------
# Draws


def test_without_a_schedule_the_draws_are_the_constant_noise_draws():
    """The original draw order, written out here: all odometry noise, then all measurement
    noise (one pair per landmark per scan), at the constant sigmas."""
    scenario, world = scenario_and_world(small_scenario())
    path = world_path(world)
    seed = np.random.SeedSequence(3)
    data = simulate(scenario, world, seed, path)
    rng = np.random.default_rng(seed)
    K = len(path.truth.u)
    u_odo = path.truth.u + rng.standard_normal((K, 2)) * np.array(SIGMAS[:2])
    noise = rng.standard_normal((len(path.geometry.steps), len(world.landmarks), 2))
    noise = noise * np.array(SIGMAS[2:])
    assert u_odo.tobytes() == data.u_odo.tobytes()
    for i, scan in enumerate(data.scans):
        z = path.geometry.range[i, scan.ids] + noise[i, scan.ids, 0]
        assert z.tobytes() == scan.z[:, 0].tobytes()


def test_a_neutral_schedule_keeps_every_draw():
    """A schedule of factor 1 takes the scheduled path and still gives the same bytes: the
    Gaussian draws are the same numbers in the same order."""
    doc = small_scenario()
    scenario, world = scenario_and_world(doc)
    neutral, _ = scenario_and_world({
        **doc, "noise_schedule": {"changes": [{"channels": ["R", "Qu"], "factor": 1, "start_s": 0}]}
    })  # fmt: skip
    seed = np.random.SeedSequence(5)
    a, b = simulate(scenario, world, seed), simulate(neutral, world, seed)
    assert a.u_odo.tobytes() == b.u_odo.tobytes()
    assert all(x.z.tobytes() == y.z.tobytes() for x, y in zip(a.scans, b.scans, strict=True))


def long_straight_run(schedule: dict, seed: int = 0, K: int = 48_000):
    """A run of K control steps (1200 s) standing still in front of 12 landmarks, all seen at
    every scan (the simulator only adds noise to the truth it is given)."""
    doc = small_scenario(world={
        "landmarks": [[5.0 + i, (-1) ** i * (1 + i % 4)] for i in range(12)],
        "waypoints": [[100, 0]],
    })  # fmt: skip
    scenario, world = scenario_and_world({**doc, "noise_schedule": schedule})
    truth = Truth(x=np.zeros((K + 1, 3)), u=np.tile([3.0, 0.0], (K, 1)))
    geometry = scan_geometry(world, truth)
    data = simulate_run(
        world, truth, SIGMAS, np.random.default_rng(seed), geometry, scenario.noise_schedule
    )
    return world, truth, geometry, data


def measurement_noise(geometry, data) -> tuple[np.ndarray, np.ndarray]:
    """(scan times (n,), noise (n, landmarks, 2)) of the scans that hold measurements."""
    rows = [(s.step, s.z - np.column_stack([geometry.range[i, s.ids], geometry.bearing[i, s.ids]]))
            for i, s in enumerate(data.scans) if len(s.ids)]  # fmt: skip
    t = np.array([r[0] for r in rows]) * 0.025
    noise = np.stack([r[1] for r in rows])
    noise[..., 1] = wrap_angle(noise[..., 1])
    return t, noise


def test_standard_deviations_per_phase_on_a_long_run():
    """Range sigma 3x on [300, 700) s, control sigmas 2x on [500, 900) s: the sample standard
    deviations of the draws, phase by phase, match (48,000 controls, 72,000 range draws)."""
    world, truth, geometry, data = long_straight_run({
        "changes": [
            {"channels": ["range"], "factor": 9, "start_s": 300, "end_s": 700},
            {"channels": ["Qu"], "factor": 4, "start_s": 500, "end_s": 900},
        ]
    })  # fmt: skip
    t_odo = np.arange(1, len(truth.u) + 1) * world.T
    odo = data.u_odo - truth.u
    for a, b, factor in ((0, 500, 1), (500, 900, 2), (900, 1201, 1)):
        m = (t_odo >= a) & (t_odo < b)
        np.testing.assert_allclose(odo[m].std(axis=0), np.array(SIGMAS[:2]) * factor, rtol=0.03)
    t, noise = measurement_noise(geometry, data)
    for a, b, factor in ((0, 300, 1), (300, 700, 3), (700, 1201, 1)):
        m = (t >= a) & (t < b)
        assert noise[m, :, 0].std() == pytest.approx(SIGMAS[2] * factor, rel=0.03)
        assert noise[m, :, 1].std() == pytest.approx(SIGMAS[3], rel=0.03)


def test_the_change_applies_from_its_exact_step():
    """Scaled standard normals: the noise of the scan at exactly start_s is already scaled,
    the one just before is not; the same at end_s (scans at 0.2 s: steps of 8 x 25 ms)."""
    schedule = {"changes": [{"channels": ["range"], "factor": 4, "start_s": 10, "end_s": 20}]}
    world, truth, geometry, data = long_straight_run(schedule, seed=1, K=1200)
    _, _, plain, plain_data = long_straight_run({"changes": [
        {"channels": ["range"], "factor": 1, "start_s": 0}]}, seed=1, K=1200)  # fmt: skip
    t, noise = measurement_noise(geometry, data)
    _, noise0 = measurement_noise(plain, plain_data)
    ratio = noise[..., 0] / noise0[..., 0]
    inside = (t >= 10 - 1e-9) & (t < 20 - 1e-9)
    np.testing.assert_allclose(ratio[inside], 2.0, rtol=1e-9)
    np.testing.assert_allclose(ratio[~inside], 1.0, rtol=1e-9)
    assert inside.sum() == 50  # 10 s of 5 Hz scans: t = 10.0, 10.2, ..., 19.8


def test_blackout_empties_exactly_its_scans():
    schedule = {"blackouts": [{"start_s": 4, "end_s": 6}]}
    _, _, geometry, data = long_straight_run(schedule, seed=2, K=1200)
    _, _, _, plain = long_straight_run(
        {"changes": [{"channels": ["R"], "factor": 1, "start_s": 0}]}, seed=2, K=1200
    )
    for scan, ref in zip(data.scans, plain.scans, strict=True):
        dark = 4 <= scan.step * 0.025 < 6
        assert len(scan.ids) == (0 if dark else 12), scan.step
        if not dark:  # the other scans keep their draws
            assert scan.z.tobytes() == ref.z.tobytes()
    assert sum(len(s.ids) == 0 for s in data.scans) == 10


def test_contaminated_outliers_share_and_window():
    """p = 0.1 at 100x variance on [50, 150) s: |noise| > 5 sigma has probability
    0.1 P(|N| > 0.5) = 0.0617 inside (and about 6e-7 outside)."""
    schedule = {"outliers": {"model": "contaminated", "probability": 0.1, "variance_factor": 100,
                             "start_s": 50, "end_s": 150}}  # fmt: skip
    _, _, geometry, data = long_straight_run(schedule, seed=3, K=8000)
    t, noise = measurement_noise(geometry, data)
    big = np.abs(noise / np.array(SIGMAS[2:])) > 5
    inside = (t >= 50) & (t < 150)
    expected = 0.1 * 2 * stats.norm.sf(0.5)
    share = big[inside].mean(axis=(0, 1))  # per channel: range, bearing
    np.testing.assert_allclose(share, expected, atol=0.006)
    assert big[~inside].sum() == 0
    # an outlier hits both components of a measurement at once
    assert (big[inside][..., 0] & big[inside][..., 1]).mean() > 0.5 * expected


def test_student_t_noise_has_the_t_distribution():
    schedule = {"outliers": {"model": "student_t", "dof": 3, "channels": ["range"]}}
    _, _, geometry, data = long_straight_run(schedule, seed=4, K=8000)
    _, noise = measurement_noise(geometry, data)
    standardised = noise / np.array(SIGMAS[2:])
    assert stats.kstest(standardised[..., 0].ravel(), stats.t(3).cdf).pvalue > 1e-3
    assert stats.kstest(standardised[..., 1].ravel(), stats.norm.cdf).pvalue > 1e-3
    assert stats.kstest(standardised[..., 0].ravel(), stats.norm.cdf).pvalue < 1e-6


def test_same_seed_same_bytes_with_outliers():
    schedule = {"outliers": {"model": "contaminated", "probability": 0.2, "variance_factor": 9}}
    a = long_straight_run(schedule, seed=6, K=800)[3]
    b = long_straight_run(schedule, seed=6, K=800)[3]
    assert a.u_odo.tobytes() == b.u_odo.tobytes()
    assert all(x.z.tobytes() == y.z.tobytes() for x, y in zip(a.scans, b.scans, strict=True))


# ---------------------------------------------------------------------------------------------
# The oracle


def test_oracle_equals_an_ekf_given_each_phase_true_noise():
    """R 16x on [5, 12) s and Qu 9x from 8 s: a plain RobotEKF whose R and Qu are set by hand to
    each phase's values gives the same trajectory, bit for bit."""
    doc = small_scenario(noise_schedule={"changes": [
        {"channels": ["R"], "factor": 16, "start_s": 5, "end_s": 12},
        {"channels": ["Qu"], "factor": 9, "start_s": 8},
    ]})  # fmt: skip
    scenario, world = scenario_and_world(doc)
    oracle_spec = next(f for f in scenario.filters if f.kind == "ekf-oracle")
    data = simulate(scenario, world, np.random.SeedSequence(8))
    oracle = build_filter(oracle_spec, scenario, world)
    assert isinstance(oracle, ScheduledOracle)
    got = run_filter(oracle, data, world, 1)

    sv, sg, sr, sb = SIGMAS
    ctx = filter_context(oracle_spec, scenario, world)
    ekf = RobotEKF(**ctx.kwargs())
    x = []
    for k in range(1, len(data.u_odo) + 1):
        t = k * world.T
        r = 16.0 if 5 <= t < 12 else 1.0
        q = 9.0 if t >= 8 else 1.0
        ekf.R = np.diag([sr**2 * r, sb**2 * r])
        ekf.Qu = np.diag([sv**2 * q, sg**2 * q])
        ekf.predict(data.u_odo[k - 1])
        if k % world.sensor_every == 0:
            scan = data.scans[k // world.sensor_every - 1]
            if len(scan.ids):
                ekf.update_scan(scan.z, world.landmarks[scan.ids])
        x.append(ekf.x.copy())
    assert not got["diverged"]
    np.testing.assert_array_equal(got["x"], np.array(x))
    # the oracle reports the true variances it was told
    t = np.arange(1, len(data.u_odo) + 1) * world.T
    np.testing.assert_allclose(got["R_diag"][:, 0], sr**2 * np.where((t >= 5) & (t < 12), 16, 1))
    np.testing.assert_allclose(got["Q_diag"][:, 1], sg**2 * np.where(t >= 8, 9, 1))


def test_scheduled_oracle_runs_on_filterpy_under_the_fast_engine():
    doc = small_scenario(
        engine="fast",
        noise_schedule={"changes": [{"channels": ["R"], "factor": 4, "start_s": 5}]},
    )
    scenario, world = scenario_and_world(doc)
    oracle, ekf = scenario.filters[2], scenario.filters[0]
    assert engine_of("fast", oracle, scenario) == "filterpy"
    assert engine_of("fast", ekf, scenario) == "fast"
    plain, _ = scenario_and_world(small_scenario(engine="fast"))
    assert engine_of("fast", plain.filters[2], plain) == "fast"
    data = simulate(scenario, world, np.random.SeedSequence(2))
    fast = run_filter_on("fast", oracle, scenario, world, data)
    ref = run_filter_on("filterpy", oracle, scenario, world, data)
    np.testing.assert_array_equal(fast["x"], ref["x"])


def test_the_plain_oracle_is_unchanged_without_a_schedule():
    scenario, world = scenario_and_world(small_scenario())
    assert filter_context(scenario.filters[2], scenario, world).true_noise is None
    assert type(build_filter(scenario.filters[2], scenario, world)) is RobotEKF


# ---------------------------------------------------------------------------------------------
# Validation: one line naming the file, the field and what is allowed


BAD_SCHEDULES = [
    ({"changes": [{"channels": ["R"], "factor": 2, "start_s": 1, "stop_s": 3}]},
     "noise_schedule.changes.0.stop_s: unknown key"
     " (allowed: channels, end_s, factor, shape, start_s)"),
    ({"changes": [{"channels": ["R"], "factor": 2, "start_s": 5, "end_s": 3}]},
     "noise_schedule.changes.0: change: end_s must be later than start_s"),
    ({"changes": [{"channels": ["R"], "factor": 2, "start_s": 5, "shape": "ramp"}]},
     "noise_schedule.changes.0: a ramp needs end_s"),
    ({"changes": [{"channels": ["wheels"], "factor": 2, "start_s": 5}]},
     "noise_schedule.changes.0.channels.0:"
     " Input should be 'speed', 'steering', 'range', 'bearing'"),
    ({"changes": [{"channels": ["R"], "factor": 0, "start_s": 5}]},
     "noise_schedule.changes.0.factor: Input should be greater than 0"),
    ({"changes": [{"channels": ["R"], "factor": 2, "start_s": -1}]},
     "noise_schedule.changes.0.start_s: Input should be greater than or equal to 0"),
    ({"changes": [{"channels": [], "factor": 2, "start_s": 1}]},
     "noise_schedule.changes.0.channels: List should have at least 1 item"),
    ({"outliers": {"model": "contaminated", "probability": 0.1}},
     "noise_schedule.outliers: contaminated outliers need probability and variance_factor"),
    ({"outliers": {"model": "student_t", "dof": 2}},
     "noise_schedule.outliers.dof: Input should be greater than 2"),
    ({"outliers": {"model": "student_t", "dof": 5, "probability": 0.1}},
     "noise_schedule.outliers: probability and variance_factor are for contaminated outliers"),
    ({"outliers": {"model": "cauchy"}},
     "noise_schedule.outliers.model: Input should be 'contaminated' or 'student_t'"),
    ({"blackouts": [{"start_s": 3, "end_s": 3}]},
     "noise_schedule.blackouts.0: blackout: end_s must be later than start_s"),
    ({"blackouts": [{"start_s": 3}]}, "noise_schedule.blackouts.0.end_s: Field required"),
    ({}, "noise_schedule: an empty schedule: give changes, outliers or blackouts"),
    ({"ramps": []}, "noise_schedule.ramps: unknown key (allowed: blackouts, changes, outliers)"),
    ({"changes": [{"channels": ["R"], "factor": True, "start_s": 1}]},
     "noise_schedule.changes.0.factor: expected a number or text, not true/false"),
]  # fmt: skip


@pytest.mark.parametrize(("schedule", "message"), BAD_SCHEDULES)
def test_bad_schedules_are_refused_in_one_line(tmp_path, schedule, message):
    path = write_scenario(tmp_path / "bad.yaml", small_scenario(noise_schedule=schedule))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: {message}"), text


def test_the_cli_refuses_a_bad_schedule_with_exit_code_2(tmp_path):
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    bad = {"changes": [{"channels": ["R"], "factor": 2, "start_s": 5, "end_s": 1}]}
    path = write_scenario(tmp_path / "bad.yaml", small_scenario(noise_schedule=bad))
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "noise_schedule.changes.0: change: end_s must be later than start_s" in result.output
    assert not (tmp_path / "out").exists()


def test_every_shipped_changing_config_loads():
    folder = Path(__file__).parents[1] / "configs" / "changing"
    files = sorted(folder.glob("*.yaml"))
    assert len(files) >= 5
    for file in files:
        scenario, _ = load_scenario(file)
        assert scenario.noise_schedule is not None
        kinds = {f.kind for f in scenario.filters}
        assert {"ekf", "ekf-oracle", "anfekf", "cm-scale", "sage-husa", "vb-r", "vbakf"} <= kinds


def test_a_sweep_can_vary_the_schedule():
    from anfekf_bench.sweeps import expand

    doc = small_scenario(
        noise_schedule={"changes": [{"channels": ["R"], "factor": 4, "start_s": 5}]},
        sweep={"axes": [{"field": "noise_schedule.changes.0.factor", "values": [2, 8, 32]}]},
    )
    cells = expand(parse_scenario(doc), Path("sweep.yaml"))
    assert [c.scenario.noise_schedule.changes[0].factor for c in cells] == [2, 8, 32]
