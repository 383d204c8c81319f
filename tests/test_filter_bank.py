"""Multiple-model banks (filters/bank.py): the rules by hand, the 1-model bank is the EKF on
both motion models, and the bank's weight goes to the true hypothesis when it is on the grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import FilterContext, RobotEKF
from anfekf_bench.filters.bank import (
    BankEKF,
    IMMSpec,
    MMAESpec,
    hypotheses,
    imm_mix,
    imm_mix_by_sums,
    innovation_loglik,
    mix_moments,
    mixture_weights,
    normalise_log_weights,
)
from anfekf_bench.filters.context import build_filter
from anfekf_bench.models import Bicycle, Unicycle, wrap_angle
from anfekf_bench.runner import simulate

from .conftest import small_scenario

ONE = {f: (1.0,) for f in ("qu_factors", "range_factors", "bearing_factors")}
rng = np.random.default_rng(23)


# ---------------------------------------------------------------------------------------------
# The rules


def test_innovation_loglik_is_the_gaussian_log_density():
    for _ in range(5):
        A = rng.normal(size=(2, 2))
        S = A @ A.T + 0.1 * np.eye(2)
        nu = rng.normal(size=2)
        nis = float(nu @ np.linalg.solve(S, nu))
        ref = multivariate_normal(mean=np.zeros(2), cov=S).logpdf(nu)
        got = innovation_loglik(nis, S[0, 0], S[0, 1], S[1, 0], S[1, 1], math.inf)
        assert got == pytest.approx(ref, rel=1e-12)
        # censored at the gate: the density at NIS = gate
        censored = innovation_loglik(nis, S[0, 0], S[0, 1], S[1, 0], S[1, 1], nis / 2)
        assert censored == pytest.approx(ref + nis / 4, rel=1e-12)
    assert innovation_loglik(1.0, 1.0, 2.0, 2.0, 1.0, math.inf) == -math.inf  # det < 0


def test_normalise_floors_in_log_space():
    logw = np.array([0.0, -5.0, -800.0, -1e5])  # exp underflows: log space keeps them apart
    ref = logw - logsumexp(logw)
    normalise_log_weights(logw, math.log(1e-30))
    floor = math.log(1e-30)
    assert logw[0] == pytest.approx(ref[0], abs=1e-12) and logw[1] == pytest.approx(ref[1])
    assert logw[2] == pytest.approx(floor, abs=1e-12) and logw[3] == pytest.approx(floor)
    assert logsumexp(logw) == pytest.approx(0.0, abs=1e-15)
    nan = np.array([0.0, math.nan])
    normalise_log_weights(nan, floor)
    assert np.isnan(nan).all()


def test_mixture_weights_drop_small_members_but_never_the_best():
    logw = np.log(np.array([0.5, 0.49995, 5e-5]))
    w = np.empty(3)
    mixture_weights(logw, 1e-4, w)
    np.testing.assert_allclose(w, [0.5 / 0.99995, 0.49995 / 0.99995, 0.0], rtol=1e-12)
    mixture_weights(np.log(np.array([0.3, 0.3, 0.4])), 0.9, w)
    np.testing.assert_array_equal(w, [0.0, 0.0, 1.0])


def test_mix_moments_by_hand_with_headings_across_the_cut():
    w = np.array([0.25, 0.75])
    X = np.array([[1.0, 2.0, math.pi - 0.1], [3.0, -2.0, -math.pi + 0.1]])
    P = np.array([np.diag([1.0, 2.0, 3.0]).ravel(), np.eye(3).ravel() * 0.5])
    x, Pm = np.empty(3), np.empty(9)
    mix_moments(w, X, P, X[1, 2], x, Pm)
    # headings about -pi + 0.1: member 0 sits at -0.2 from it, so the mean is -pi + 0.1 - 0.05
    h = -math.pi + 0.05
    assert x == pytest.approx([2.5, -1.0, h], abs=1e-14)
    d = np.array([[-1.5, 3.0, -0.15], [0.5, -1.0, 0.05]])
    terms = zip(w, P, d, strict=True)
    ref = sum(wi * (Pi.reshape(3, 3) + np.outer(di, di)) for wi, Pi, di in terms)
    np.testing.assert_allclose(Pm.reshape(3, 3), ref, atol=1e-14)


def dense_mixture(mu: np.ndarray, X: np.ndarray, P: np.ndarray, j: int):
    """Member j's mixed start by the textbook: the weighted mean (heading around member j's) and
    the weighted covariance with the spread of the means."""
    dh = wrap_angle(X[:, 2] - X[j, 2])
    xj = np.array([mu @ X[:, 0], mu @ X[:, 1], wrap_angle(X[j, 2] + mu @ dh)])
    D = X - xj
    D[:, 2] = wrap_angle(D[:, 2])
    return xj, sum(mu[i] * (P[i].reshape(3, 3) + np.outer(D[i], D[i])) for i in range(len(mu)))


def test_imm_mix_equals_the_dense_textbook_interaction():
    M, p_stay = 4, 0.9
    w = rng.dirichlet(np.ones(M))
    X = np.column_stack([rng.normal(size=(M, 2)), rng.uniform(-3, 3, M)])
    P = np.array([(A @ A.T + np.eye(3)).ravel() for A in rng.normal(size=(M, 3, 3))])
    Pi = np.full((M, M), (1 - p_stay) / (M - 1)) + (p_stay - (1 - p_stay) / (M - 1)) * np.eye(M)
    c = Pi.T @ w  # c_j = sum_i p_ij w_i
    logw = np.log(w)
    X0, P0 = np.empty_like(X), np.empty_like(P)
    imm_mix(logw, p_stay, 0.0, X, P, X0, P0, *(np.empty(M) for _ in range(3)), np.empty(3),
            np.empty(9), np.empty(M, np.int64), np.empty(M, np.int64))  # fmt: skip
    np.testing.assert_allclose(np.exp(logw), c, rtol=1e-12)
    for j in range(M):
        mu = Pi[:, j] * w / c[j]
        xj, Pj = dense_mixture(mu, X, P, j)
        np.testing.assert_allclose(X0[j], xj, atol=1e-12)
        np.testing.assert_allclose(P0[j].reshape(3, 3), Pj, atol=1e-12)


def test_imm_mix_with_a_threshold_equals_the_dense_rule():
    """The members that cannot reach the threshold are skipped without their division: the
    starts equal the dense rule's (every mu_i|j computed, those below the threshold dropped)."""
    M, p_stay, threshold = 60, 0.98, 1e-4
    w = rng.dirichlet(np.full(M, 0.05))  # a few heavy members, many light, some near the cut
    w[7] = 1.2e-4  # one near the threshold (mu_7|j is about w_7 for a light member j)
    w /= w.sum()
    X = np.column_stack([rng.normal(size=(M, 2)), rng.uniform(-3, 3, M)])
    P = np.array([(A @ A.T + np.eye(3)).ravel() for A in rng.normal(size=(M, 3, 3))])
    p_off = (1 - p_stay) / (M - 1)
    Pi = np.full((M, M), p_off) + (p_stay - p_off) * np.eye(M)
    c = Pi.T @ w
    logw = np.log(w)
    X0, P0 = np.empty_like(X), np.empty_like(P)
    imm_mix(logw, p_stay, threshold, X, P, X0, P0, *(np.empty(M) for _ in range(3)),
            np.empty(3), np.empty(9), np.empty(M, np.int64), np.empty(M, np.int64))  # fmt: skip
    np.testing.assert_allclose(np.exp(logw), c, rtol=1e-12)
    kept = 0
    for j in range(M):
        mu = Pi[:, j] * w / c[j]
        keep = (mu >= threshold) | (np.arange(M) == j)
        kept += keep.sum()
        mu = np.where(keep, mu, 0.0) / mu[keep].sum()
        xj, Pj = dense_mixture(mu, X, P, j)
        np.testing.assert_allclose(X0[j], xj, atol=1e-12)
        np.testing.assert_allclose(P0[j].reshape(3, 3), Pj, atol=1e-12)
    assert M < kept < M * M  # some starts mix several members, none mixes all


def _both_interactions(logw, p_stay, threshold, X, P):
    """(logw, X0, P0) of `imm_mix` (the dense rule) and of `imm_mix_by_sums`."""
    M = len(logw)
    out = []
    for by_sums in (False, True):
        lw, X0, P0 = logw.copy(), np.empty((M, 3)), np.empty((M, 9))
        scratch = [*(np.empty(M) for _ in range(3)), np.empty(3), np.empty(9),
                   np.empty(M, np.int64), np.empty(M, np.int64)]  # fmt: skip
        if by_sums:
            scratch += [np.empty(M, np.int64), np.empty(M + 1), np.empty((M + 1, 3)),
                        np.empty((M + 1, 9)), np.empty(M + 1)]  # fmt: skip
        (imm_mix_by_sums if by_sums else imm_mix)(lw, p_stay, threshold, X, P, X0, P0, *scratch)
        out.append((lw, X0, P0))
    return out


def _members(M, heading, spread):
    X = np.column_stack([rng.normal(10, 0.05, M), rng.normal(-5, 0.05, M),
                         wrap_angle(rng.normal(heading, spread, M))])  # fmt: skip
    A = rng.normal(0, 0.01, (M, 3, 3))
    return X, (A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)).reshape(M, 9)


@pytest.mark.parametrize(
    "p_stay, threshold", [(0.98, 1e-4), (0.6, 0.0), (0.999, 1e-2), (1.0, 1e-4)]
)
@pytest.mark.parametrize("heading, spread", [(0.3, 0.01), (3.13, 0.02), (-1.0, 0.8), (0.0, 2.5)])
def test_the_interaction_by_running_sums_equals_the_dense_rule(p_stay, threshold, heading, spread):
    """imm_mix_by_sums (the fast engine's) against imm_mix (the reference): the same predicted
    weights to the bit, the same starts to 1e-12 of their scale; headings about the cut at
    +-pi (3.13) and spread past SUMS_HEADING_SPREAD (2.5: those members take the dense rule);
    weights from one dominant member to many near the threshold, and floored ones."""
    for M in (1, 2, 7, 125):
        for weights in ("dominant", "spread", "floored"):
            scale = {"dominant": 40.0, "spread": 1.0, "floored": 3.0}[weights]
            logw = rng.normal(0.0, scale, M)
            if weights == "floored":
                logw[rng.integers(0, M, size=max(1, M // 2))] = -69.0  # weight 1e-30
            logw -= logsumexp(logw)
            X, P = _members(M, heading, spread)
            (l1, x1, p1), (l2, x2, p2) = _both_interactions(logw, p_stay, threshold, X, P)
            np.testing.assert_array_equal(l2, l1)
            np.testing.assert_allclose(x2[:, :2], x1[:, :2], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(wrap_angle(x2[:, 2] - x1[:, 2]), 0.0, atol=1e-12)
            np.testing.assert_allclose(p2, p1, rtol=0, atol=1e-12 * np.abs(p1).max())


def test_the_interaction_by_running_sums_takes_the_dense_rule_for_weights_not_finite():
    M = 9
    logw = np.log(np.full(M, 1.0 / M))
    logw[4] = np.nan
    X, P = _members(M, 0.0, 0.01)
    (l1, x1, p1), (l2, x2, p2) = _both_interactions(logw, 0.98, 1e-4, X, P)
    np.testing.assert_array_equal(l2, l1)
    np.testing.assert_array_equal(x2, x1)
    np.testing.assert_array_equal(p2, p1)


def test_grid_of_hypotheses_and_validation():
    spec = MMAESpec(name="b", kind="mmae")
    H = hypotheses(spec)
    assert H.shape == (125, 4) == (spec.n_models(), 4)
    assert sorted(set(H[:, 0])) == pytest.approx([0.1, 10**-0.5, 1, 10**0.5, 10])
    np.testing.assert_array_equal(H[:, 0], H[:, 1])  # both controls together by default
    sep = MMAESpec(
        name="b", kind="mmae", qu_factors=(1,), v_factors=(0.1, 1), gamma_factors=(1, 10),
        range_factors=(1,), bearing_factors=(1,),
    )  # fmt: skip
    grid = [[0.1, 1, 1, 1], [0.1, 10, 1, 1], [1, 1, 1, 1], [1, 10, 1, 1]]
    assert hypotheses(sep).tolist() == grid
    assert hypotheses(MMAESpec(name="b", kind="mmae", adaptation=False)).tolist() == [[1] * 4]
    with pytest.raises(ValueError, match="bounds"):
        MMAESpec(name="b", kind="mmae", bounds=(0.5, 2.0))
    with pytest.raises(ValueError, match="at most"):
        MMAESpec(name="b", kind="mmae", range_factors=(1.0,) * 50, bearing_factors=(1.0,) * 50)
    with pytest.raises(ValueError):
        IMMSpec(name="b", kind="imm", p_stay=0.0)


# ---------------------------------------------------------------------------------------------
# Whole runs


def _run(entry: dict, filter_noise: dict, true_noise: dict | None = None, seed: int = 3, **kw):
    doc = small_scenario(record_every=1, filter_noise=filter_noise, **kw)
    if true_noise:
        doc["true_noise"] = true_noise
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, {"name": "f", **entry}]
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, ".")
    data = simulate(scenario, world, np.random.SeedSequence(seed))
    ekf = build_filter(scenario.filters[0], scenario, world)
    flt = build_filter(scenario.filters[1], scenario, world)
    return run_filter(ekf, data, world, 1), run_filter(flt, data, world, 1), flt


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_one_model_bank_is_the_ekf_bicycle(kind):
    ref, out, _ = _run({"kind": kind, **ONE, "v_factors": (1.0,)}, {"sigma_range": 2.0})
    for key in ("x", "P", "R_diag", "Q_diag", "P_infl"):
        np.testing.assert_allclose(out[key], ref[key], rtol=0, atol=1e-12, err_msg=key)
    for key in ("n_updates", "n_rejected", "diverged"):
        assert out[key] == ref[key]
    assert out["nis_sum"] == pytest.approx(ref["nis_sum"], rel=1e-12)


def _drive(flt, model_steps):
    """Step a filter through (u, dt, zs, landmarks) events as the event engine does."""
    xs, Ps = [], []
    for u, dt, zs, lms in model_steps:
        flt.predict(u, dt=dt)
        if len(zs):
            flt.update_scan(zs, lms)
        xs.append(flt.x.copy())
        Ps.append(flt.P.copy())
    return np.array(xs), np.array(Ps)


def _unicycle_events(n=120):
    """A robot circling two landmarks with noisy range-bearing readings, variable steps."""
    model = Unicycle(0.12)
    lms = np.array([[4.0, 1.0], [-1.0, 5.0]])
    x = np.array([0.0, 0.0, 0.3])
    events = []
    for k in range(n):
        dt = 0.12 + 0.03 * math.sin(k)
        u = np.array([0.5, 0.3])
        x = model.f(x, u, dt)
        zs = []
        if k % 3 == 0:
            for lm in lms:
                d = lm - x[:2]
                zs.append(
                    [
                        np.hypot(*d) + rng.normal(0, 0.05),
                        wrap_angle(math.atan2(d[1], d[0]) - x[2] + rng.normal(0, 0.02)),
                    ]
                )
        events.append((u, dt, np.array(zs).reshape(-1, 2), lms if zs else lms[:0]))
    return events


def _ctx(model):
    return FilterContext(
        x0=np.array([0.1, -0.1, 0.25]), P0=np.eye(3) * 0.05, Qu=np.diag([0.02, 0.05]),
        R=np.diag([0.01, 0.001]), model=model, dt=0.12, gate=13.8,
    )  # fmt: skip


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_one_model_bank_is_the_ekf_unicycle(kind):
    events = _unicycle_events()
    ctx = _ctx(Unicycle(0.12))
    spec = (IMMSpec if kind == "imm" else MMAESpec)(name="b", kind=kind, **ONE)
    x_ref, P_ref = _drive(RobotEKF(**ctx.kwargs()), events)
    x_out, P_out = _drive(spec.build(ctx), events)
    np.testing.assert_allclose(x_out, x_ref, atol=1e-12)
    np.testing.assert_allclose(P_out, P_ref, atol=1e-12)


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_bank_runs_on_the_unicycle_and_stays_consistent(kind):
    events = _unicycle_events()
    spec = (IMMSpec if kind == "imm" else MMAESpec)(
        name="b", kind=kind, qu_factors=(0.1, 1, 10), range_factors=(0.1, 1), bearing_factors=(1,)
    )
    flt = spec.build(_ctx(Unicycle(0.12)))
    x, P = _drive(flt, events)
    assert np.isfinite(x).all() and all(np.linalg.eigvalsh(p).min() > 0 for p in P)
    assert math.isclose(np.exp(flt.logw).sum(), 1.0, rel_tol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_the_weight_goes_to_the_true_hypothesis(kind):
    """True noise on the grid (Qu x 0.1, range x 10 of the assumed): after a run of the small
    world, the bank puts (nearly) all its weight on that member."""
    grid = {"qu_factors": (0.1, 1.0, 10.0), "range_factors": (0.1, 1.0, 10.0),
            "bearing_factors": (1.0,)}  # fmt: skip
    assumed = {"sigma_v": 0.3, "sigma_gamma_deg": 3.0, "sigma_range": 0.1}
    true = {"sigma_v": 0.3 * 0.1**0.5, "sigma_gamma_deg": 3.0 * 0.1**0.5,
            "sigma_range": 0.1 * 10**0.5}  # fmt: skip
    weights = []
    for loops in (1, 3):
        world = {**small_scenario()["world"], "loops": loops}
        _, out, flt = _run({"kind": kind, **grid}, assumed, true, world=world)
        assert isinstance(flt, BankEKF) and not out["diverged"]
        w = np.exp(flt.logw)
        best = int(np.argmax(w))
        assert flt.factors[best].tolist() == pytest.approx([0.1, 0.1, 10.0, 1.0])
        weights.append(w[best])
    # MMAE: tends to 1; IMM: to its stationary share under switching (p_stay 0.98)
    if kind == "mmae":  # static: tends to 1
        assert weights[0] < weights[1] and weights[1] > 1 - 1e-9
        rel = 1e-6
    else:  # switching: to a stationary share (2 % leaves each scan, the likelihood returns it)
        assert min(weights) > 0.8
        return  # its recorded Qu, an arithmetic mean, is pulled up by the 10x members' share
    # the recorded R and Qu are the weighted hypotheses': the true ones at the end
    assert out["Q_diag"][-1] == pytest.approx(np.diag(flt.Qu0) * 0.1, rel=rel)
    assert out["R_diag"][-1] == pytest.approx(np.diag(flt.R0) * [10.0, 1.0], rel=rel)


def test_bicycle_bank_is_used_by_the_registry():
    ref, out, flt = _run({"kind": "mmae", "qu_factors": (0.5, 1.0)}, {})
    assert isinstance(flt, BankEKF) and isinstance(flt.model, Bicycle) and len(flt.members) == 50


@pytest.mark.parametrize("kind", ["mmae", "imm"])
def test_one_scan_by_hand(kind):
    """A 2-member bank (range variance x1, x10), one predict and a scan of two landmarks: the
    weights are the normalised products of each member's Gaussian innovation densities (B.1,
    B.2), the estimate their mixture (B.3); for the IMM then the interaction (B.4)."""
    ctx = _ctx(Bicycle(0.1, 2.0))
    spec = (IMMSpec if kind == "imm" else MMAESpec)(
        name="b", kind=kind, qu_factors=(1.0,), range_factors=(1.0, 10.0), bearing_factors=(1.0,)
    )
    bank = spec.build(ctx)
    lms = np.array([[6.0, 2.0], [1.0, 7.0]])
    zs = np.array([[6.3, 0.05], [6.8, 1.15]])
    u = np.array([1.0, 0.1])
    members, logl = [], []
    for f in (1.0, 10.0):
        m = RobotEKF(**{**ctx.kwargs(), "R": ctx.R @ np.diag([f, 1.0])})
        m.predict(u)
        ll = 0.0
        for z, lm in zip(zs, lms, strict=True):
            inn = m.innovation(z, lm)
            S = inn.HPHt + m.R
            ll += multivariate_normal(np.zeros(2), S).logpdf(inn.nu)
            m.update_landmark(z, lm)
        members.append(m)
        logl.append(ll)
    w = np.exp(np.array(logl) - logsumexp(logl))
    bank.predict(u)
    bank.update_scan(zs, lms)
    assert w.min() > 1e-4  # both in the mixture
    x = w[0] * members[0].x + w[1] * members[1].x
    d = [m.x - x for m in members]
    P = sum(wi * (m.P + np.outer(di, di)) for wi, m, di in zip(w, members, d, strict=True))
    np.testing.assert_allclose(bank.x, x, atol=1e-12)
    np.testing.assert_allclose(bank.P, P, atol=1e-12)
    if kind == "mmae":
        np.testing.assert_allclose(np.exp(bank.logw), w, rtol=1e-10)
        np.testing.assert_allclose(np.diag(bank.R), w @ np.array([[0.01, 0.001], [0.1, 0.001]]))
    else:  # B.4: c = Pi^T w with p_stay 0.98 and the members restarted from their mixed starts
        Pi = np.array([[0.98, 0.02], [0.02, 0.98]])
        c = Pi.T @ w
        np.testing.assert_allclose(np.exp(bank.logw), c, rtol=1e-10)
        for j, mem in enumerate(bank.members):
            mu = Pi[:, j] * w / c[j]
            xj = mu[0] * members[0].x + mu[1] * members[1].x
            np.testing.assert_allclose(mem.x, xj, atol=1e-12)
