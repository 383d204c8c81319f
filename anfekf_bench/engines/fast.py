"""The fast engine (SPEC 11): the built-in filters as plain numeric kernels over one run.

`run_filter_fast` returns exactly what `filterpy_engine.run_filter` returns (same keys, shapes,
dtypes and meaning, divergence included), so metrics, storage and the report are shared. The
kernels (`kernels.py`) are compiled by numba when it is installed (the `fast` extra) and run as
plain Python otherwise; `JIT` says which.

What it runs (`supports`): the EKF, the oracle EKF, ekf-ml and ekf-tuned (fitted noise), the
ANFEKF with any of its parameters (adapt R, Q or RQ, adaptation and learning on or off,
adapt_from, bounds, window, rates, ...), `cm-scale` (the ANFEKF's kernel with its proportional
rule), the multiple-model banks `mmae` and `imm` with any of theirs (`kernels.run_bank_kernel`),
the fading-factor EKF (`kernels.run_fading_kernel`), and `akhlaghi`, `vb-r`, `vbakf`, `swvb`,
`sage-husa` and `iae` in every mode (`kernels.run_akhlaghi_kernel`, `run_vbr_kernel`,
`run_vbakf_kernel`, `run_swvb_kernel`, `run_sage_husa_kernel`, `run_iae_kernel`), `als`
in every mode (`kernels_als.run_als_kernel`) and the trained `kalmannet`
(`kernels_kalmannet.run_kalmannet_kernel`, its weights passed as arrays); each family's rules
are the plain functions of its filter module, called by both engines; on both motion models
(the bicycle of the simulated scenarios, the unicycle of recorded logs: a kernel argument).
Anything else (a user's own filter) is not implemented here: the caller runs it on filterpy.

Its input is the one contract of a run, a `timeline.Timeline` (a simulated run through
`timeline.from_run`, a recorded span through `timeline.timeline`): every kernel loops over its
stamps (predict with u[k] over dt[k]; the stamp's landmarks as one scan; record if record[k]).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..config import World
from ..filters import anfis
from ..filters.akhlaghi import AkhlaghiSpec
from ..filters.als import ALSSpec
from ..filters.anfekf import ANFEKFSpec
from ..filters.bank import IMMSpec, MMAESpec, hypotheses
from ..filters.cm_scale import CMScaleSpec
from ..filters.ekf import EKFSpec
from ..filters.fading import FadingSpec
from ..filters.iae import IAESpec
from ..filters.kalmannet import KalmanNetSpec
from ..filters.kalmannet_net import KalmanNetWeights
from ..filters.registry import register_engine
from ..filters.sage_husa import SageHusaSpec
from ..filters.spec import FilterContext, FilterSpec
from ..filters.swvb import SWVBSpec
from ..filters.vb import VBAKFSpec, VBRSpec
from ..filters.vb_bank import R_RULE_CODE, VBIMMSpec, member_factors
from ..models import Bicycle, Unicycle
from ..sources.simulator import RunData
from ..timeline import Timeline, from_run
from ..timeline import clear_cache as clear_timeline_cache
from . import kernels as _jit_kernels
from . import kernels_als as _jit_kernels_als
from . import kernels_default as _jit_kernels_default
from . import kernels_kalmannet as _jit_kernels_kalmannet
from .fast_support import SUPPORTED_SPECS, supported_type  # noqa: F401  (SUPPORTED_SPECS: re-exported)

JIT: bool = _jit_kernels.JIT  # True when the kernels are numba-compiled


def supports(spec: FilterSpec, model: object | None = None) -> bool:
    """Whether the fast engine implements this filter (else run it on filterpy); with `model`,
    also whether it implements that motion model (the bicycle and the unicycle)."""
    return supported_type(spec) and (model is None or _motion(model) is not None)


def _motion(model: object) -> tuple[int, float, float] | None:
    """The kernels' (motion, B, T0) for a motion model; None for one they do not implement."""
    if type(model) is Bicycle:  # exactly these (a subclass may change the maths)
        return _jit_kernels.MOTION_BICYCLE, float(model.B), 0.0
    if type(model) is Unicycle:
        return _jit_kernels.MOTION_UNICYCLE, 0.0, float(model.T0)
    return None


register_engine("fast", supports)  # what `anfekf kinds` and the registry's capabilities report


def clear_cache() -> None:
    """Forget the last run's timeline (the bench times making it too)."""
    clear_timeline_cache()


# ---------------------------------------------------------------------------------------------
# The entry point


def _pure_kernels():
    return _jit_kernels.pure_module()


def _matrix(a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape != (n, n):
        raise ValueError(f"expected a {n}x{n} matrix, got shape {a.shape}")
    return np.ascontiguousarray(a).ravel()


def run_filter_fast(
    spec: FilterSpec,
    ctx: FilterContext,
    tl: Timeline | RunData,
    world: World | None = None,
    record_every: int = 0,
    *,
    jit: bool = True,
) -> dict:
    """Run one filter over one run's timeline like `filterpy_engine.run_filter(spec.build(ctx),
    tl)`, on the motion model of `ctx.model` (bicycle or unicycle).

    A simulated run may be passed as (RunData, world, record_every): `timeline.from_run` makes
    its timeline (record_every 0: no records; the per-run counts are still returned). A filter
    that stops being finite and positive definite is marked diverged and its remaining records
    stay NaN, as on filterpy. `jit=False` runs the plain-Python kernels even when numba is
    installed.
    """
    if not supports(spec):
        raise ValueError(f"the fast engine does not implement filter kind {spec.kind!r}")
    motion = _motion(ctx.model)
    if motion is None:
        raise ValueError(
            "the fast engine implements the bicycle and the unicycle motion models, "
            f"not {type(ctx.model)}"
        )
    if not isinstance(tl, Timeline):
        tl = from_run(tl, world, record_every)
    run = _run_args(tl, motion)
    n = int(np.count_nonzero(tl.record))
    record = run[-1]
    x = np.full((n, 3), np.nan)
    P = np.full((n, 3, 3), np.nan)
    R = np.full((n, 2), np.nan)
    Qu = np.full((n, 2), np.nan)
    # Without numba the module's own kernels are already plain Python.
    k = _pure_kernels() if (JIT and not jit) else _jit_kernels

    if isinstance(spec, KalmanNetSpec):
        return _run_kalmannet(spec, ctx, run, x, P, R, Qu, n, jit)
    if isinstance(spec, ALSSpec):
        ka = _jit_kernels_als.pure_module() if (JIT and not jit) else _jit_kernels_als
        diverged, j, nis_sum, n_updates, n_rejected = ka.run_als_kernel(
            *_common_args(ctx, run),
            "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation),
            spec.adapt_from == "all", float(spec.bounds[0]), float(spec.bounds[1]),
            int(spec.lags), int(spec.window), int(spec.every), int(spec.warmup),
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, VBIMMSpec):
        kd = _jit_kernels_default.pure_module() if (JIT and not jit) else _jit_kernels_default
        diverged, j, nis_sum, n_updates, n_rejected = _run_vb_imm(kd, spec, ctx, run, x, P, R, Qu)
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, MMAESpec):
        diverged, j, nis_sum, n_updates, n_rejected = _run_bank(k, spec, ctx, run, x, P, R, Qu)
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, AkhlaghiSpec):
        diverged, j, nis_sum, n_updates, n_rejected = k.run_akhlaghi_kernel(
            *_common_args(ctx, run),
            "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation),
            spec.adapt_from == "all", float(spec.bounds[0]), float(spec.bounds[1]),
            float(spec.alpha),
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, VBAKFSpec):
        P_infl = np.full(n, np.nan)
        diverged, j, nis_sum, n_updates, n_rejected = k.run_vbakf_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all",
            float(spec.bounds[0]), float(spec.bounds[1]),
            float(spec.rho), int(spec.iterations), float(spec.tau), float(spec.tau_R),
            spec.R_structure == "diagonal",
            record, x, P, R, Qu, P_infl,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected, P_infl)
    if isinstance(spec, SWVBSpec):
        diverged, j, nis_sum, n_updates, n_rejected = k.run_swvb_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all",
            float(spec.bounds[0]), float(spec.bounds[1]),
            float(spec.rho), int(spec.iterations), float(spec.a0),
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, VBRSpec):
        diverged, j, nis_sum, n_updates, n_rejected = k.run_vbr_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all",
            float(spec.bounds[0]), float(spec.bounds[1]),
            float(spec.rho), int(spec.iterations), float(spec.alpha0),
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, FadingSpec):
        P_infl = np.full(n, np.nan)
        diverged, j, nis_sum, n_updates, n_rejected = k.run_fading_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all", int(spec.window),
            float(spec.bounds[1]),
            record, x, P, R, Qu, P_infl,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected, P_infl)
    if isinstance(spec, SageHusaSpec):
        diverged, j, nis_sum, n_updates, n_rejected = k.run_sage_husa_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all", *(float(b) for b in spec.bounds),
            "Q" in spec.adapt, float(spec.b), int(spec.warmup), spec.q_sample == "unbiased",
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, IAESpec):
        diverged, j, nis_sum, n_updates, n_rejected = k.run_iae_kernel(
            *_common_args(ctx, run),
            bool(spec.adaptation), spec.adapt_from == "all", *(float(b) for b in spec.bounds),
            spec.adapt == "Q", int(spec.window), spec.hph == "window",
            spec.nonpositive == "hold", spec.q_form == "full", int(spec.q_window),
            record, x, P, R, Qu,
        )  # fmt: skip
        return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)
    if isinstance(spec, ANFEKFSpec):
        adapt_R, adapt_Q = "R" in spec.adapt, "Q" in spec.adapt
        anf = _anfis_rows(spec)
        eta_m, eta_d, eta_w = (float(e) for e in spec.learning_rate)
        lo, hi = (float(b) for b in spec.bounds)
        adaptation, learning = bool(spec.adaptation), bool(spec.learning)
        from_all, window, clip = spec.adapt_from == "all", int(spec.window), float(spec.output_clip)
    elif isinstance(spec, CMScaleSpec):  # the ANFEKF's supervisor with the proportional rule
        adapt_R, adapt_Q = "R" in spec.adapt, "Q" in spec.adapt
        adaptation, learning = bool(spec.adaptation), False
        anf = np.zeros((3, _jit_kernels.N_ANFIS))
        eta_m = eta_d = eta_w = 0.0
        lo, hi = (float(b) for b in spec.bounds)
        from_all, window, clip = spec.adapt_from == "all", int(spec.window), float(spec.output_clip)
    else:
        adapt_R = adapt_Q = adaptation = learning = False
        anf = np.zeros((3, _jit_kernels.N_ANFIS))
        eta_m = eta_d = eta_w = 0.0
        lo, hi = 1.0, 1.0
        from_all, window, clip = True, 1, 1.0
    if isinstance(spec, CMScaleSpec):
        rule, kappa = _jit_kernels.RULE_PROPORTIONAL, float(spec.kappa)
    else:
        rule, kappa = _jit_kernels.RULE_ANFIS, 1.0
    diverged, j, nis_sum, n_updates, n_rejected = k.run_kernel(
        *_common_args(ctx, run),
        adapt_R, adapt_Q, adaptation, learning, from_all, lo, hi, window, clip,
        eta_m, eta_d, eta_w, anf, rule, kappa,
        record, x, P, R, Qu,
    )  # fmt: skip
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)


def _run_args(tl: Timeline, motion: tuple[int, float, float]) -> tuple:
    """The timeline and the model as the kernels read them: (u, dt, lm, xy, z, motion, B, T0,
    record), contiguous, the dtypes the compiled signatures expect."""
    return (
        np.ascontiguousarray(tl.u, dtype=float).reshape(-1, 2),
        np.ascontiguousarray(tl.dt, dtype=float),
        np.ascontiguousarray(tl.lm, dtype=np.int64),
        np.ascontiguousarray(tl.xy, dtype=float).reshape(-1, 2),
        np.ascontiguousarray(tl.z, dtype=float).reshape(-1, 2),
        *motion,
        np.ascontiguousarray(tl.record, dtype=np.bool_),
    )


def _common_args(ctx: FilterContext, run: tuple) -> tuple:
    """The arguments every kernel starts with: the run (controls, steps, scans), the model
    (motion, B, T0), the start (x0, P0), the noise (Qu, R) and the gate."""
    has_gate = ctx.gate is not None
    return (
        *run[:8],
        np.ascontiguousarray(ctx.x0, dtype=float).reshape(3), _matrix(ctx.P0, 3),
        _matrix(ctx.Qu, 2), _matrix(ctx.R, 2),
        float(ctx.gate) if has_gate else math.inf, has_gate,
    )  # fmt: skip


def _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected, P_infl=None) -> dict:
    """The run's dict, as filterpy_engine.run_filter returns it."""
    if P_infl is None:
        P_infl = np.ones(n)  # these filters never inflate P-
    if diverged:
        x[j:] = P[j:] = R[j:] = Qu[j:] = P_infl[j:] = np.nan
    return {
        "x": x,
        "P": P,
        "R_diag": R,
        "Q_diag": Qu,
        "P_infl": P_infl,
        "diverged": bool(diverged),
        "nis_sum": float(nis_sum),
        "n_updates": int(n_updates),
        "n_rejected": int(n_rejected),
    }


def _run_kalmannet(spec: KalmanNetSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit):
    """filters.kalmannet.KalmanNetFilter on `kernels_kalmannet.run_kalmannet_kernel`: the
    spec's trained weights (`with_fit`: the fit of the simulated or the recorded training, from
    the run store's cache or just trained) as arrays."""
    weights = spec.trained_weights
    kk = _jit_kernels_kalmannet.pure_module() if (JIT and not jit) else _jit_kernels_kalmannet
    diverged, j, nis_sum, n_updates, n_rejected = kk.run_kalmannet_kernel(
        *_common_args(ctx, run), weights.net, weights.scales, run[-1], x, P, R, Qu,
    )  # fmt: skip
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)


def _run_bank(k, spec: MMAESpec, ctx: FilterContext, run: tuple, x, P, R, Qu):
    """filters.bank.BankEKF on `kernels.run_bank_kernel`."""
    factors = hypotheses(spec)
    Qu_m = np.ascontiguousarray(factors[:, :2] * np.diag(ctx.Qu))
    R_m = np.ascontiguousarray(factors[:, 2:] * np.diag(ctx.R))
    has_gate = ctx.gate is not None
    censor_at = ctx.gate if (spec.adapt_from == "accepted" and has_gate) else math.inf
    imm = isinstance(spec, IMMSpec)
    return k.run_bank_kernel(
        *run[:8],
        np.ascontiguousarray(ctx.x0, dtype=float).reshape(3), _matrix(ctx.P0, 3),
        Qu_m, R_m, float(ctx.gate) if has_gate else math.inf, has_gate,
        float(censor_at), math.log(spec.weight_floor), float(spec.mixture_threshold), imm,
        float(spec.p_stay) if imm else 1.0,
        run[8], x, P, R, Qu,
    )  # fmt: skip


def _run_vb_imm(kd, spec: VBIMMSpec, ctx: FilterContext, run: tuple, x, P, R, Qu):
    """filters.vb_bank.VBIMMEKF on `kernels_default.run_vb_imm_kernel`."""
    factors = member_factors(spec)
    Qu_m = np.ascontiguousarray(np.outer(factors[:, 0], np.diag(ctx.Qu)))
    R_m = np.ascontiguousarray(factors[:, 1:] * np.diag(ctx.R))
    has_gate = ctx.gate is not None
    censor_at = ctx.gate if (spec.adapt_from == "accepted" and has_gate) else math.inf
    rule = R_RULE_CODE[spec.r_rule] if spec.adaptation else R_RULE_CODE["grid"]
    return kd.run_vb_imm_kernel(
        *run[:8],
        np.ascontiguousarray(ctx.x0, dtype=float).reshape(3), _matrix(ctx.P0, 3),
        Qu_m, R_m, _matrix(ctx.R, 2), float(ctx.gate) if has_gate else math.inf, has_gate,
        rule, spec.adapt_from == "all", float(spec.bounds[0]), float(spec.bounds[1]),
        float(spec.rho), int(spec.iterations), float(spec.alpha0), float(spec.b),
        float(censor_at), float(spec.likelihood_dof), math.log(spec.weight_floor),
        float(spec.mixture_threshold), float(spec.p_stay) if spec.adaptation else 1.0,
        run[8], x, P, R, Qu,
    )  # fmt: skip


def _anfis_rows(spec: ANFEKFSpec) -> np.ndarray:
    """The starting ANFIS parameters as ANFEKF.__init__ makes them, one kernel row each: the
    R-ANFIS of range and of bearing (rows 0, 1) and the Q-ANFIS (row 2); a fresh copy (the
    kernel trains them in place)."""
    key = (
        tuple(spec.centres_d), float(spec.width_d), tuple(spec.centres_dd),
        float(spec.width_dd), float(spec.singleton_scale),
    )  # fmt: skip
    return _anfis_start(*key).copy()


@functools.lru_cache(maxsize=64)
def _anfis_start(
    centres_d: tuple, width_d: float, centres_dd: tuple, width_dd: float, singleton_scale: float
) -> np.ndarray:
    r_init = anfis.init_params(
        centres0=centres_d, width0=width_d, centres1=centres_dd, width1=width_dd,
        singleton_scale=singleton_scale,
    )  # fmt: skip
    # The Q-ANFIS's inputs d_11 and d_22 are two mismatches of the same scale.
    q_init = anfis.init_params(
        centres0=centres_d, width0=width_d, centres1=centres_d, width1=width_d,
        singleton_scale=singleton_scale,
    )  # fmt: skip
    rows = np.empty((3, _jit_kernels.N_ANFIS))
    for i, p in enumerate((r_init, r_init, q_init)):
        rows[i] = np.concatenate([p.m.ravel(), p.delta.ravel(), p.w])
    rows.setflags(write=False)
    return rows


# The kernels `warm_up` calls directly (their callees compile, and are cached, with them).
WARM_UP_KERNELS = (
    (_jit_kernels, "run_kernel"), (_jit_kernels, "run_akhlaghi_kernel"),
    (_jit_kernels, "run_vbr_kernel"), (_jit_kernels, "run_vbakf_kernel"),
    (_jit_kernels, "run_swvb_kernel"), (_jit_kernels, "run_sage_husa_kernel"),
    (_jit_kernels, "run_iae_kernel"), (_jit_kernels_als, "run_als_kernel"),
    (_jit_kernels_kalmannet, "run_kalmannet_kernel"),
)  # fmt: skip
COMPILE_ESTIMATE = "about 1-2 min"  # results/bench.json: fast_compile_s 47 s on 2 free cores


def kernels_cached() -> bool | None:
    """Whether numba's on-disk cache holds every kernel `warm_up` compiles, valid for this
    source (numba checks the file's stamp): False means the first fast run compiles them (a
    minute or two); None when the kernels are not compiled (no numba) or the cache cannot be
    inspected (numba's FunctionCache API changed: say nothing rather than something wrong)."""
    if not JIT:
        return None
    try:
        return all(
            bool(getattr(module, name)._cache._cache_file._load_index())
            for module, name in WARM_UP_KERNELS
        )
    except Exception:  # a private numba API: any change means "unknown"
        return None


def warm_up(jit: bool = True) -> float:
    """Compile (or load from numba's cache) every kernel signature the engine uses by running
    a tiny EKF, ANFEKF (and cm-scale: the same kernel), akhlaghi, vb-r, vbakf, swvb, Sage-Husa,
    IAE, ALS and KalmanNet (a small random network); returns the seconds it took."""
    import time

    from ..sources.simulator import Scan, Truth

    t0 = time.perf_counter()
    world = _tiny_world()
    K = 16
    u = np.tile([3.0, 0.01], (K, 1))
    scans = tuple(
        Scan(step=8 * (i + 1), ids=np.array([0]), z=np.array([[10.0, 0.1]])) for i in range(K // 8)
    )
    data = RunData(truth=Truth(x=np.zeros((K + 1, 3)), u=u), u_odo=u, scans=scans)
    ctx = FilterContext(
        x0=np.zeros(3), P0=np.eye(3) * 1e-9, Qu=np.diag([0.09, 0.003]), R=np.diag([0.01, 3e-4]),
        model=Bicycle(world.T, world.B), dt=world.T, gate=13.8,
    )  # fmt: skip
    specs = (
        EKFSpec(name="ekf"), ANFEKFSpec(name="anfekf", kind="anfekf", adapt="RQ"),
        AkhlaghiSpec(name="akhlaghi", kind="akhlaghi"), VBRSpec(name="vb-r", kind="vb-r"),
        VBAKFSpec(name="vbakf", kind="vbakf"), SWVBSpec(name="swvb", kind="swvb"),
        SageHusaSpec(name="sage-husa", kind="sage-husa", adapt="RQ"),
        IAESpec(name="iae", kind="iae", adapt="Q"), ALSSpec(name="als", kind="als"),
        KalmanNetSpec.model_construct(name="kalmannet", kind="kalmannet").with_weights(
            KalmanNetWeights.random(hidden_size=4)
        ),
    )  # fmt: skip
    for spec in specs:
        run_filter_fast(spec, ctx, data, world, 1, jit=jit)
    clear_cache()
    return time.perf_counter() - t0


def _tiny_world() -> World:
    return World(
        landmarks=np.array([[10.0, 1.0]]), waypoints=np.array([[20.0, 0.0]]), loops=1,
        x0=np.zeros(3), V=3.0, B=4.0, max_steer=0.5, max_steer_rate=0.35, T=0.025,
        sensor_every=8, max_range=20.0, half_fov=math.pi / 2, waypoint_tolerance=1.0,
        max_steps=100,
    )  # fmt: skip
