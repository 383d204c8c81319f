"""`ekf-ml` on recorded data (issue 25): the EKF whose noise maximises the innovation likelihood of
the very run it is scored on, never its ground truth (fitting.own.fit_on_own_innovations on
engines.tuning's kernel)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from anfekf_bench.engines.events import run_filter_events, timeline
from anfekf_bench.engines.tuning import DIVERGED, TimelineLikelihood, fit_noise
from anfekf_bench.filters.ekf import RobotEKF, gate_threshold
from anfekf_bench.filters.fitted import EKFMLSpec
from anfekf_bench.fitting.own import fit_on_own_innovations, own_innovations
from anfekf_bench.models import Unicycle
from anfekf_bench.real_experiment import SegmentInputs, recorded_run
from anfekf_bench.sources import mrclam as m
from anfekf_bench.sources.recorded import Segment, parse_real_scenario

from .synthetic_drive import synthetic_drive

TRUE = np.array([0.05, 0.15, 0.08, 0.03])  # sv [m/s], sw [rad/s], sr [m], sb [rad]
P0 = np.eye(3) * 0.05**2
GATE = gate_threshold(0.999)


class LikelihoodEKF(RobotEKF):
    """RobotEKF on filterpy that sums log|S| + nu^T S^-1 nu over every associated innovation
    (`all`) and over the accepted ones only (`accepted`)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.all = 0.0
        self.accepted = 0.0

    def update_landmark(self, z, landmark):
        inn = self.innovation(z, landmark)
        S = inn.HPHt + self.R
        term = math.log(np.linalg.det(S)) + float(inn.nu @ np.linalg.solve(S, inn.nu))
        self.all += term
        accepted = super().update_landmark(z, landmark)
        self.accepted += term if accepted else 0.0
        return accepted


def reference(tl, x0, sig, p0=P0) -> LikelihoodEKF:
    sv, sw, sr, sb = sig
    flt = LikelihoodEKF(
        x0=np.array(x0, float), P0=p0, Qu=np.diag([sv * sv, sw * sw]),
        R=np.diag([sr * sr, sb * sb]), model=Unicycle(0.12), dt=0.12, gate=GATE,
    )  # fmt: skip
    run_filter_events(flt, tl)
    return flt


def drive_span(drive: str, t0: float, t1: float, period=0.12) -> SegmentInputs:
    from anfekf_bench.real_experiment import segment_inputs

    log = m.load_drive(drive)
    pose = np.array(m.interpolate_truth(log, t0))
    rec = type("Rec", (), {"log": log, "scorable": staticmethod(lambda t: m.scorable(log, t))})
    return segment_inputs(rec, Segment(0, t0, t1, t0, pose, t1 - t0), period)


def scenario(**change):
    doc = {
        "name": "own", "protocol": "drives",
        "data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r2", "d7-r1"]},
        "starts": [1],
        "filters": [{"name": "ekf", "kind": "ekf"},
                    {"name": "ekf-ml", "kind": "ekf-ml", "starts": [1.0], "max_evaluations": 60}],
    }  # fmt: skip
    doc.update(change)
    return parse_real_scenario(doc)


# ------------------------------------------------------------------ the objective


@pytest.mark.parametrize("where", ["synthetic", "d6-r2"])
def test_objective_equals_the_robot_ekf_summed_nll(where):
    """The kernel's sum of log|S| + nu^T S^-1 nu over every associated innovation, and its gate
    decisions, equal RobotEKF's on filterpy to 1e-9, on a synthetic drive and on 60 s of a real
    one (65 Hz odometry thinned to 8 Hz scores), with settings that gate and lose lock."""
    if where == "synthetic":
        tl, x0, _ = synthetic_drive(5, TRUE, seconds=60.0)
    else:
        inp = drive_span("d6-r2", 100.0, 160.0)
        tl, x0 = inp.timeline, inp.segment.pose
    problem = TimelineLikelihood.of(tl, x0, P0, GATE, 0.12)
    rejected = 0
    for sig in (TRUE, TRUE * [4, 0.5, 0.3, 0.2], TRUE * [0.2, 3, 1, 4]):
        ref = reference(tl, x0, sig)
        status, nll, n_upd, n_rej = problem.nll(sig)
        assert status != DIVERGED
        assert nll == pytest.approx(ref.all, rel=1e-9)
        assert (n_upd, n_rej) == (ref.n_updates, ref.n_rejected)
        got = problem.evaluate(sig)
        assert got["nll_per_innovation"] == pytest.approx(ref.all / len(tl.z), rel=1e-9)
        assert got["innovations"] == ref.n_updates + ref.n_rejected
        rejected += n_rej
    assert rejected > 0  # the gate acted


def test_the_objective_does_not_depend_on_units_and_the_accepted_only_sum_does():
    """Every associated innovation counts, so a change of units (metres to millimetres) adds the
    same constant to every setting: the better setting stays better. The sum over accepted
    updates only runs over a set that depends on the setting: in millimetres it prefers a
    sigma_range three times too small, which rejects a quarter of the measurements."""
    tl, x0, _ = synthetic_drive(1, TRUE, seconds=120.0)
    mm = np.array([1000.0, 1.0, 1000.0, 1.0])  # sv, sw, sr, sb in mm units
    tl_mm = replace(tl, u=tl.u * [1000.0, 1.0], z=tl.z * [1000.0, 1.0], xy=tl.xy * 1000.0)
    P0_mm = np.diag([2500.0, 2500.0, 0.05**2])
    tight = TRUE * [1, 1, 0.3, 1]
    out = {}
    for units, t, p0, scale in (("m", tl, P0, 1.0), ("mm", tl_mm, P0_mm, mm)):
        problem = TimelineLikelihood.of(t, np.zeros(3), p0, GATE, 0.12)
        for name, sig in (("true", TRUE), ("tight", tight)):
            flt = reference(t, np.zeros(3), sig * scale, p0)
            out[units, name] = (problem.nll(sig * scale)[1], flt.accepted, flt.n_rejected)
    # the objective: the true noise wins in both units, by the same margin
    for units in ("m", "mm"):
        assert out[units, "true"][0] < out[units, "tight"][0]
    shift = out["mm", "true"][0] - out["m", "true"][0]
    assert shift == pytest.approx(len(tl.z) * math.log(1e6), rel=1e-6)
    assert out["mm", "tight"][0] - out["m", "tight"][0] == pytest.approx(shift, rel=1e-6)
    # the accepted-only sum: right in metres, wrong in millimetres
    assert out["m", "true"][1] < out["m", "tight"][1]
    assert out["mm", "tight"][1] < out["mm", "true"][1]
    assert out["mm", "tight"][2] > 0.2 * len(tl.z) > 10 * out["mm", "true"][2]


# ------------------------------------------------------------------ the fit


@pytest.mark.parametrize("seed", [1, 2])
def test_ekf_ml_recovers_the_true_sigmas_of_a_synthetic_drive(seed):
    """On an 8-minute drive generated from a known unicycle with known noise (variable dt, about
    4000 to 8000 landmark measurements), the fit from a start 2x off on every sigma lands within
    15 % of the true sigmas."""
    tl, x0, _ = synthetic_drive(seed, TRUE, seconds=480.0)
    start = TRUE * [2.0, 0.5, 2.0, 0.5]
    problem = TimelineLikelihood.of(tl, x0, P0, GATE, 0.12)
    found = fit_noise(problem, "likelihood", start, [1.0, 3.0], 300)
    np.testing.assert_allclose(found["sigmas"], TRUE, rtol=0.15)
    assert found["training"]["nll_per_innovation"] < found["start"]["nll_per_innovation"]


def test_no_truth_is_read():
    """The objective holds no ground truth, and a run whose truth is NaN everywhere gets the
    same fit, bit for bit."""
    sc = scenario()
    inp = drive_span("d6-r2", 100.0, 220.0)
    blind = replace(inp, truth=np.full_like(inp.truth, np.nan), scored=np.zeros_like(inp.scored))
    own = own_innovations(sc, inp)
    assert not any("truth" in f for f in vars(own.problem))
    a = fit_on_own_innovations(sc, [inp], ["a"], None)[1]["filters"]["ekf-ml"]["runs"][0]
    b = fit_on_own_innovations(sc, [blind], ["a"], None)[1]["filters"]["ekf-ml"]["runs"][0]
    a.pop("seconds"), b.pop("seconds")  # the time the fit took
    assert a == b and a["fingerprint"] == b["fingerprint"]


def test_fits_are_cached_by_fingerprint_and_recorded(tmp_path):
    sc = scenario()
    inputs = [drive_span("d6-r2", 100.0, 160.0), drive_span("d7-r1", 100.0, 160.0)]
    inputs[1] = replace(inputs[1], segment=replace(inputs[1].segment, index=1))
    noise, record = fit_on_own_innovations(sc, inputs, ["d6-r2", "d7-r1"], tmp_path)
    assert record["fitted_now"] == 2 and sorted(noise) == [0, 1]
    assert len(list(tmp_path.glob("fit-*.json"))) == 2
    again, rec2 = fit_on_own_innovations(sc, inputs, ["d6-r2", "d7-r1"], tmp_path)
    assert again == noise and rec2["fitted_now"] == 0
    runs = rec2["filters"]["ekf-ml"]["runs"]
    assert [r["cached"] for r in runs] == [True, True]
    assert [r["label"] for r in runs] == ["d6-r2", "d7-r1"]
    assert "never its ground truth" in rec2["filters"]["ekf-ml"]["uses"]
    for r in runs:
        assert r["evaluations"] <= 60 + 2 and r["seconds"] > 0
        assert r["at_fit"]["nll_per_innovation"] <= r["start"]["nll_per_innovation"]
    assert json.dumps(rec2)
    # another filter setting is another fit
    other = scenario(filters=[{"name": "ekf-ml", "kind": "ekf-ml", "starts": [3.0],
                               "max_evaluations": 60}])  # fmt: skip
    _, rec3 = fit_on_own_innovations(other, inputs[:1], ["d6-r2"], tmp_path)
    assert rec3["fitted_now"] == 1


def test_ekf_ml_runs_once_with_its_fitted_noise():
    """One instance (no naive starts), built from the run's fit: its estimates are those of the
    reference engine's EKF with the fitted sigmas."""
    sc = scenario()
    assert sc.instance_names() == ["ekf x1", "ekf-ml"]
    inp = drive_span("d6-r2", 100.0, 160.0)
    noise, _ = fit_on_own_innovations(sc, [inp], ["d6-r2"], None)
    fitted = noise[0]
    run = recorded_run(sc, inp, None, len(inp.t), fitted)
    sig = [fitted["ekf-ml"][k] for k in ("sigma_v", "sigma_w_rad", "sigma_range",
                                        "sigma_bearing_rad")]  # fmt: skip
    ref = reference(inp.timeline, inp.segment.pose, sig)
    np.testing.assert_allclose(run["filters"]["ekf-ml"]["x"], ref_states(inp, sig), atol=0)
    assert run["filters"]["ekf-ml"]["n_updates"] == ref.n_updates


def ref_states(inp, sig):
    sv, sw, sr, sb = sig
    flt = RobotEKF(
        x0=np.array(inp.segment.pose, float), P0=P0, Qu=np.diag([sv * sv, sw * sw]),
        R=np.diag([sr * sr, sb * sb]), model=Unicycle(0.12), dt=0.12, gate=GATE,
    )  # fmt: skip
    return run_filter_events(flt, inp.timeline)["x"]


def test_recorded_scenarios_accept_ekf_ml_and_no_other_fitted_kind():
    from anfekf_bench.config import ScenarioError

    assert scenario().filters[1].kind == "ekf-ml"
    assert isinstance(scenario().filters[1], EKFMLSpec)
    with pytest.raises(ScenarioError):
        scenario(filters=[{"name": "t", "kind": "ekf-tuned", "starts": [1.0]}])


def test_a_likelihood_fit_refuses_the_rmse_criterion():
    own = own_innovations(scenario(), drive_span("d6-r2", 100.0, 110.0))
    with pytest.raises(ValueError, match="likelihood"):
        own.fit_noise("rmse", [1.0], 10)


def test_timeline_of_a_drive_has_every_landmark():
    """The objective sees every landmark measurement of the span (thinning merges predicts only)."""
    log = m.load_drive("d6-r2")
    full = timeline(m.events(log, 100.0, 160.0))
    inp = drive_span("d6-r2", 100.0, 160.0)
    assert np.array_equal(own_innovations(scenario(), inp).problem.z, full.z)


def test_segments_protocol_fits_ekf_ml_per_held_out_segment(tmp_path):
    """The segment protocol takes ekf-ml too: one fit per held-out segment, on its own data."""
    import yaml
    from typer.testing import CliRunner

    from anfekf_bench.cli import app
    from anfekf_bench.storage import read_json, read_steps

    from .test_real_data import user_scenario

    path = user_scenario(tmp_path)
    doc = yaml.safe_load(path.read_text())
    ml = {"name": "ekf-ml", "kind": "ekf-ml", "starts": [1.0], "max_evaluations": 30}
    doc["filters"] = [{"name": "ekf-tuned", "kind": "ekf-tuned"}, ml]
    doc["claims"] = []
    path.write_text(yaml.safe_dump(doc))
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    folder = tmp_path / "out" / "my-robot"
    manifest = read_json(folder / "manifest.json")
    assert [f["name"] for f in manifest["filters"]] == ["ekf-tuned", "ekf-ml"]
    runs = manifest["fits"]["filters"]["ekf-ml"]["runs"]
    assert [r["label"] for r in runs] == ["0", "1"]
    assert len({r["sigma_v"] for r in runs}) == 2  # each segment its own fit
    steps = read_steps(folder)
    assert np.isfinite(steps[steps["filter"] == "ekf-ml"]["pos_err"]).any()
