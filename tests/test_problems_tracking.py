"""The tracking radar (SPEC 17): its transitions against the continuous dynamics (matrix
exponentials), H against finite differences, the simulator's noise against Q and R, the EKF with
the true noise consistent, the gate's counts, the compiled filter against the Python loop, the
truth-tuned fit, the scenario keys' one-line errors (exit 2 through the CLI), seeds, and the
registry's word on ALS."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError
from anfekf_bench.filters.registry import supports_problem, unsupported_reason
from anfekf_bench.problems.base import wrap
from anfekf_bench.problems.experiment import run_one, run_rng
from anfekf_bench.problems.filters import GenericKF
from anfekf_bench.problems.kalman import ekf_nll
from anfekf_bench.problems.schema import parse_problem_scenario
from anfekf_bench.problems.scoring import score
from anfekf_bench.problems.tracking import TrackingProblem, Turn, transition
from anfekf_bench.problems.tracking_schema import TrackingSystem

from .conftest import write_scenario

# The continuous dynamics of (x, vx, y, vy) turning at rate w: dx = vx, dvx = -w vy, dy = vy,
# dvy = w vx; the white acceleration enters the velocities.
L_NOISE = np.array([[0, 0], [1, 0], [0, 0], [0, 1]], dtype=float)


def continuous(w: float) -> np.ndarray:
    return np.array([[0, 1, 0, 0], [0, 0, 0, -w], [0, 0, 0, 1], [0, w, 0, 0]], dtype=float)


def problem(**over) -> TrackingProblem:
    return TrackingSystem(**over).problem()


def doc(**over) -> dict:
    d = {"name": "trk", "problem": "tracking", "runs": 2, "seed": 3,
         "filters": [{"name": "kf", "kind": "ekf"}]}  # fmt: skip
    d.update(over)
    return d


@pytest.mark.parametrize("w", [0.0, 0.05, -0.2, 1e-7])
def test_transition_is_the_exponential_of_the_continuous_dynamics(w):
    for T in (0.5, 1.0, 3.0):
        assert np.allclose(transition(T, w), expm(continuous(w) * T), rtol=0, atol=1e-9)


def test_q_is_the_discretised_white_acceleration():
    """Van Loan: Q = integral_0^T e^(A t) L q L^T e^(A^T t) dt for A the NCV dynamics."""
    T, q = 2.0, 0.7
    A = continuous(0.0)
    M = np.zeros((8, 8))
    M[:4, :4], M[:4, 4:], M[4:, 4:] = -A, q * L_NOISE @ L_NOISE.T, A.T
    E = expm(M * T)
    Q_ref = E[4:, 4:].T @ E[:4, 4:]
    p = problem(T=T, q=q)
    assert np.allclose(p.Q, Q_ref, rtol=1e-10, atol=1e-12)
    assert p.G(p.x0, 0).shape == (4, 4) and np.array_equal(p.G(p.x0, 0), np.eye(4))


def finite_difference(fn, x, eps=1e-6):
    cols = []
    for i in range(len(x)):
        d = np.zeros(len(x))
        d[i] = eps * max(1.0, abs(x[i]))
        cols.append((fn(x + d) - fn(x - d)) / (2 * d[i]))
    return np.column_stack(cols)


@pytest.mark.parametrize("known", [False, True])
def test_jacobians_match_finite_differences_in_and_out_of_the_turn(known):
    p = problem(radar=[120.0, -300.0], manoeuvre={"omega": 0.08, "start": 5, "end": 9,
                                                   "known": known})  # fmt: skip
    rng = np.random.default_rng(0)
    for k in (0, 5, 8, 9):
        x = np.array([2000.0, 10.0, 5000.0, -15.0]) + rng.normal(0, [500, 5, 500, 5])
        assert np.allclose(p.F(x, k), finite_difference(lambda s, k=k: p.f(s, k), x), atol=1e-7)
        numeric = finite_difference(lambda s, k=k: wrap(p.h(s, k), p.angles), x)
        assert np.allclose(p.H(x, k), numeric, rtol=1e-6, atol=1e-12)
    turning = transition(1.0, 0.08)
    assert np.array_equal(p.truth_transition(6), turning)
    assert np.array_equal(p.F(x, 6), turning if known else transition(1.0, 0.0))
    assert np.array_equal(p.truth_transition(9), transition(1.0, 0.0))  # end is exclusive


def test_bearing_behind_the_radar_wraps():
    p = problem(radar=[0.0, 0.0])
    x = np.array([-1000.0, 0, 1e-3, 0])  # bearing just below pi
    z = np.array([1000.0, -np.pi + 1e-4])  # measured just above -pi
    nu = wrap(z - p.h(x, 0), p.angles)
    assert abs(nu[1]) < 1e-3


def test_simulated_noise_has_the_true_covariances():
    p = problem(steps=12_000, gate=None, manoeuvre={"omega": 0.05, "start": 100, "end": 200})
    t = p.simulate(np.random.default_rng(11))
    w = np.array([t.x[k + 1] - p.truth_transition(k) @ t.x[k] for k in range(p.steps - 1)])
    v = wrap(t.z - np.array([p.h(x, 0) for x in t.x]), p.angles)
    assert np.allclose(np.cov(w.T) / np.sqrt(np.outer(np.diag(p.Q), np.diag(p.Q))),
                       p.Q / np.sqrt(np.outer(np.diag(p.Q), np.diag(p.Q))), atol=0.04)  # fmt: skip
    assert np.allclose(np.diag(np.cov(v.T)) / np.diag(p.R), 1.0, atol=0.04)
    assert abs(np.corrcoef(v.T)[0, 1]) < 0.04


def test_the_ekf_with_the_true_noise_is_consistent():
    p = problem()
    nees, gated = [], 0
    for i in range(25):
        t = p.simulate(run_rng(7, i))
        x, P, _, dropped = p.fast_filter(p.Q, p.R, t.z)
        e = t.x - x
        nees.append(np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0]))
        gated += dropped
    anees = float(np.mean(nees))
    assert 3.7 < anees < 4.3, anees  # n = 4; 25 x 200 correlated steps
    assert gated < 25 * 200 * 0.004  # the 0.999 gate drops about 0.1 %


def test_the_compiled_filter_is_the_python_loop():
    p = problem(manoeuvre={"omega": 0.1, "start": 40, "end": 90}, gate=0.99)
    t = p.simulate(np.random.default_rng(5))
    Q, R = 0.2 * p.Q, 3.0 * p.R  # wrong, so that the turn makes the gate drop some
    trace = GenericKF(p, Q, R).run(t.z)
    x, P, nll, dropped = p.fast_filter(Q, R, t.z)
    assert trace.gated == dropped > 0
    assert np.allclose(x, trace.x, rtol=1e-9, atol=1e-9)
    assert np.allclose(P, trace.P, rtol=1e-9, atol=1e-12)
    ungated = p.fast_filter(Q, R, t.z, gated=False)
    assert ungated[3] == 0
    assert ungated[2] == pytest.approx(ekf_nll(p, t.z, Q, R), rel=1e-10)


def test_gate_counts():
    """The gate drops exactly the measurements whose normalised innovation (recomputed from
    the filter's own prior) exceeds the threshold, and there the estimate is the prior; with the
    true noise a gate of 0.99 drops about 1 %; no gate drops none."""
    p = problem(gate=0.99, manoeuvre={"omega": 0.1, "start": 60, "end": 100})
    t = p.simulate(np.random.default_rng(3))
    Q, R = 0.3 * p.Q, p.R
    trace = GenericKF(p, Q, R).run(t.z)
    x, P = p.x0, p.P0
    outside = []
    for k in range(p.steps):
        nu = wrap(t.z[k] - p.h(x, k), p.angles)
        H = p.H(x, k)
        nis = nu @ np.linalg.solve(H @ P @ H.T + R, nu)
        outside.append(nis > p.gate)
        if outside[-1]:
            assert np.array_equal(trace.x[k], x) and np.allclose(trace.P[k], P, rtol=1e-12)
        F = p.F(trace.x[k], k)
        x, P = F @ trace.x[k], F @ trace.P[k] @ F.T + Q
    assert trace.gated == sum(outside) > 0
    assert p.gate == pytest.approx(9.2103, abs=1e-4)  # chi-square 0.99, 2 dof
    steady = problem(gate=0.99)
    dropped = sum(steady.fast_filter(p.Q, p.R, steady.simulate(run_rng(2, i)).z)[3]
                  for i in range(20))  # fmt: skip
    assert 0.005 < dropped / (20 * p.steps) < 0.03
    free = problem(gate=None)
    assert GenericKF(free, 0.3 * p.Q, p.R).run(t.z).gated == 0


def test_an_outlier_is_dropped_and_counted():
    p = problem(gate=0.999)
    t = p.simulate(np.random.default_rng(1))
    z = t.z.copy()
    z[60, 0] += 1000.0  # 100 sigma of range
    clean, spoiled = GenericKF(p, p.Q, p.R).run(t.z), GenericKF(p, p.Q, p.R).run(z)
    assert spoiled.gated == clean.gated + 1
    assert np.allclose(spoiled.x[60], transition(1.0, 0.0) @ spoiled.x[59])


def test_scoring_counts_the_gated_per_filter():
    scenario = parse_problem_scenario(doc(system={"steps": 40, "gate": 0.8},
                                          filters=[{"name": "kf", "kind": "ekf"},
                                                   {"name": "o", "kind": "ekf-oracle"}]),
                                      "x.yaml")  # fmt: skip
    results = [run_one(scenario, 3, i, {}) for i in range(3)]
    truth = np.stack([x for x, _ in results])
    traces = {n: [tr[n] for _, tr in results] for n in ("kf", "o")}
    specs = {s.name: s for s in scenario.filters}
    tables = score(scenario.build_problem(), truth, traces, specs, "o", 3)
    per_run = [t.gated for t in traces["kf"]]
    assert tables["runs"].query("filter == 'kf'")["gated"].tolist() == per_run
    assert tables["summary"].set_index("filter").loc["kf", "gated"] == np.mean(per_run)
    assert sum(per_run) > 0


def test_runs_are_seeded_and_paired():
    scenario = parse_problem_scenario(doc(system={"steps": 30}), "x.yaml")
    (xa, ta), (xb, tb) = run_one(scenario, 9, 4, {}), run_one(scenario, 9, 4, {})
    assert np.array_equal(xa, xb) and np.array_equal(ta["kf"].x, tb["kf"].x)
    assert not np.array_equal(xa, run_one(scenario, 9, 5, {})[0])
    assert not np.array_equal(xa, run_one(scenario, 10, 4, {})[0])


def test_assumed_noise_defaults_to_the_truth_and_scales():
    p = parse_problem_scenario(doc(), "x.yaml")
    Q, R = p.assumed_noise()
    truth = p.build_problem()
    assert np.array_equal(Q, truth.Q) and np.array_equal(R, truth.R)
    Q, R = parse_problem_scenario(doc(filter_noise={"Q_scale": 0.1, "R_scale": 10}),
                                  "x.yaml").assumed_noise()  # fmt: skip
    assert np.allclose(Q, 0.1 * truth.Q) and np.allclose(R, 10 * truth.R)


def test_the_truth_tuned_fit_recovers_the_scale_of_a_wrong_q():
    scenario = parse_problem_scenario(doc(filter_noise={"Q_scale": 0.1},
                                          filters=[{"name": "t", "kind": "ekf-tuned"}]),
                                      "x.yaml")  # fmt: skip
    p = scenario.build_problem()
    runs = [p.simulate(run_rng(3, i, training=True)) for i in range(15)]
    Q, R, record = scenario.filters[0].fit_training(p, runs, *scenario.assumed_noise())
    assert record["converged"] and record["training_runs"] == 15
    assert 0.5 < record["Q_factor"] * 0.1 < 2.0  # the true q, within a factor 2
    assert 0.5 < record["R_factor"] < 2.0
    assert abs(record["training_anees"] - 4) < 0.1  # the level was fitted to NEES = n
    assert np.allclose(Q, record["Q_factor"] * 0.1 * p.Q)
    assert np.allclose(R, record["R_factor"] * p.R)


@pytest.mark.parametrize(
    ("over", "field", "words"),
    [
        ({"system": {"q": 0}}, "system.q", "greater than 0"),
        ({"system": {"F": [[1.0]]}}, "system.F", "unknown key"),
        ({"system": {"x0": [1, 2, 3]}}, "system", "x0: expected 4 values"),
        ({"system": {"gate": 1.0}}, "system.gate", "less than 1"),
        ({"system": {"manoeuvre": {"omega": 0.1, "start": 50, "end": 40}}},
         "system.manoeuvre", "end: after start"),
        ({"system": {"manoeuvre": {"omega": 0.1, "start": 50, "end": 500}}}, "system",
         "at most steps"),
        ({"system": {"manoeuvre": {"omega": 0, "start": 1, "end": 4}}}, "system.manoeuvre",
         "other than 0"),
        ({"system": {"x0": [0, 1, 0, 1]}}, "system", "at the radar"),
        ({"filters": [{"name": "a", "kind": "als"}]}, "", "filters.0: kind 'als' does not run"),
        ({"filter_noise": {"Q_scale": 0.1, "Q": [[1]]}}, "filter_noise", "give one"),
        ({"filter_noise": {"R": [[1, 0], [0, 1], [0, 0]]}}, "", "2 x 2"),
    ],
)  # fmt: skip
def test_bad_tracking_scenarios_are_one_line_errors(over, field, words):
    with pytest.raises(ScenarioError) as exc:
        parse_problem_scenario(doc(**over), "bad.yaml")
    message = str(exc.value)
    assert "\n" not in message and message.startswith("bad.yaml: ")
    assert words in message and exc.value.field.startswith(field)


def test_a_bad_tracking_file_exits_2(tmp_path):
    path = write_scenario(tmp_path / "bad.yaml", doc(system={"sigma_range": -1}))
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "system.sigma_range" in result.output and "Traceback" not in result.output


def test_the_registry_says_which_kinds_run_on_tracking():
    for kind in ("ekf", "ekf-oracle", "sage-husa", "vb-r", "ekf-ml", "ekf-tuned"):
        assert supports_problem(kind, "tracking") and unsupported_reason(kind, "tracking") is None
    assert not supports_problem("als", "tracking")
    assert "linear time-invariant" in unsupported_reason("als", "tracking")
    assert "ANFIS" in unsupported_reason("anfekf", "tracking")


def test_the_turn_dataclass_is_half_open():
    turn = Turn(0.1, 3, 5)
    assert [turn.rate(k) for k in range(7)] == [0, 0, 0, 0.1, 0.1, 0, 0]


def test_the_truth_tuned_fit_runs_the_python_loop_where_there_is_no_compiled_filter():
    scenario = parse_problem_scenario(
        {"name": "lin", "problem": "linear", "system": {"steps": 60},
         "filter_noise": {"Q_scale": 0.2, "R_scale": 1.0},
         "filters": [{"name": "t", "kind": "ekf-tuned", "tolerance": 0.05}]}, "x.yaml",
    )  # fmt: skip
    p = scenario.build_problem()
    assert p.fast_filter(p.Q, p.R, np.zeros((60, 2))) is None
    runs = [p.simulate(run_rng(4, i, training=True)) for i in range(3)]
    Q, R, record = scenario.filters[0].fit_training(p, runs, *scenario.assumed_noise())
    assert record["Q_factor"] * 0.2 > 0.3  # moved towards the true Q (factor 5 from the start)
    assert np.allclose(Q, record["Q_factor"] * 0.2 * p.Q)
