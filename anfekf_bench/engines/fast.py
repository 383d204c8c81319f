"""The fast engine (SPEC 11): the built-in filters as plain numeric kernels over one run.

`run_filter_fast` returns exactly what `filterpy_engine.run_filter` returns (same keys, shapes,
dtypes and meaning, divergence included), so metrics, storage and the report are shared. The
kernels (`kernels.py`) are compiled by numba when it is installed (the `fast` extra) and run as
plain Python otherwise; `JIT` says which.

What it runs (`supports`): every built-in kind (fast_support.py), on both motion models (the
bicycle of the simulated scenarios, the unicycle of recorded logs: a kernel argument). A family
that runs as one EKF (the EKF and its fitted and oracle forms, the ANFEKF, cm-scale, sage-husa,
iae, akhlaghi, vb-r, vbakf, fading) runs on the one loop (`loop.run_loop`, its steps in
`engines/families/`, compiled per family by `loop.compiled_loop`); the banks `mmae`, `imm` and
`vb-imm` on one bank kernel (`kernels_bank.run_bank_kernel`); `swvb`, `als`, the augmented EKFs
and the trained `kalmannet` on kernels of their own (`kernels_swvb`, `kernels_als`,
`kernels_augmented`, `kernels_kalmannet`, its weights passed as arrays). Each family's rules
are the plain functions of its filter module, called by both engines. Anything else (a user's
own filter) is not implemented here: the caller runs it on filterpy.

Its input is the one contract of a run, a `timeline.Timeline` (a simulated run through
`timeline.from_run`, a recorded span through `timeline.timeline`): every kernel loops over its
stamps (predict with u[k] over dt[k]; the stamp's landmarks as one scan; record if record[k]).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..analysis import metrics as _metrics
from ..analysis import run_means as _run_means
from ..config import World
from ..filters.als import ALSSpec
from ..filters.augmented import PARAMETERS, AugmentedSpec, augment_of
from ..filters.bank import IMMSpec, MMAESpec, hypotheses
from ..filters.kalmannet import KalmanNetSpec
from ..filters.kalmannet_net import KalmanNetWeights
from ..filters.registry import SPECS as REGISTERED_SPECS
from ..filters.registry import kind_of, register_engine
from ..filters.spec import FilterContext, FilterSpec, fast_family_of, fast_kernel_of
from ..filters.swvb import SWVBSpec
from ..filters.vb_bank import R_RULE_CODE, VBIMMSpec, member_factors
from ..models import Bicycle, Unicycle
from ..sources.simulator import RunData
from ..timeline import Timeline, from_run
from ..timeline import clear_cache as clear_timeline_cache
from . import families
from . import kernels as _jit_kernels
from . import kernels_als as _jit_kernels_als
from . import kernels_augmented as _jit_kernels_augmented
from . import kernels_bank as _jit_kernels_bank
from . import kernels_kalmannet as _jit_kernels_kalmannet
from . import kernels_swvb as _jit_kernels_swvb
from . import loop as _loop
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
    x = np.full((n, 3), np.nan)
    P = np.full((n, 3, 3), np.nan)
    R = np.full((n, 2), np.nan)
    Qu = np.full((n, 2), np.nan)
    # Without numba the modules' own kernels are already plain Python.
    if augment_of(spec) is not None:  # ekf-aug, or a family's `augment:`
        return run_augmented(spec, ctx, run, x, P, R, Qu, n, jit)[0]
    if families.for_spec(spec) is not None:
        return _run_family(spec, ctx, run, x, P, R, Qu, n, jit)
    return KERNEL_RUNNERS[fast_kernel_of(spec)](spec, ctx, run, x, P, R, Qu, n, jit)


def _run_bank(spec: FilterSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit) -> dict:
    """A bank (filters.bank.BankEKF, filters.vb_bank.VBIMMEKF) on the one bank kernel,
    `kernels_bank.run_bank_kernel`."""
    kb = _jit_kernels_bank.pure_module() if (JIT and not jit) else _jit_kernels_bank
    bank_args = _vb_imm_args if isinstance(spec, VBIMMSpec) else _bank_args
    diverged, j, nis_sum, n_updates, n_rejected = kb.run_bank_kernel(
        *run[:8], *bank_args(kb, spec, ctx), run[8], x, P, R, Qu
    )
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)


def _run_als(spec: ALSSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit) -> dict:
    """filters.als.ALSEKF on `kernels_als.run_als_kernel`."""
    ka = _jit_kernels_als.pure_module() if (JIT and not jit) else _jit_kernels_als
    diverged, j, nis_sum, n_updates, n_rejected = ka.run_als_kernel(
        *_common_args(ctx, run),
        "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation),
        spec.adapt_from == "all", float(spec.bounds[0]), float(spec.bounds[1]),
        int(spec.lags), int(spec.window), int(spec.every), int(spec.warmup),
        run[-1], x, P, R, Qu,
    )  # fmt: skip
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)


def _run_swvb(spec: SWVBSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit) -> dict:
    """filters.swvb.SWVBEKF on `kernels_swvb.run_swvb_kernel`."""
    ks = _jit_kernels_swvb.pure_module() if (JIT and not jit) else _jit_kernels_swvb
    diverged, j, nis_sum, n_updates, n_rejected = ks.run_swvb_kernel(
        *_common_args(ctx, run),
        bool(spec.adaptation), spec.adapt_from == "all",
        float(spec.bounds[0]), float(spec.bounds[1]),
        float(spec.rho), int(spec.iterations), float(spec.a0),
        run[-1], x, P, R, Qu,
    )  # fmt: skip
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected)


def _run_family(spec: FilterSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit) -> dict:
    """A family of the loop (`engines/families`, `loop.compiled_loop`)."""
    pure = JIT and not jit
    family = families.for_spec(spec, pure)
    run_loop = _loop.pure_module().run_loop if pure else _loop.compiled_loop(family)
    P_infl = np.full(n, np.nan)
    fam = family.params(spec, ctx)
    if hasattr(family, "for_run"):  # arrays sized by the run (loop.py: the optional `for_run`)
        fam = family.for_run(fam, run[2])
    diverged, j, nis_sum, n_updates, n_rejected = run_loop(
        fam, *_common_args(ctx, run), run[-1], x, P, R, Qu, P_infl
    )
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected, P_infl)


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


def run_augmented(spec: FilterSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit):
    """filters.augmented.AugmentedEKF (or an adaptive family's filter with `augment:`) on
    `kernels_augmented.run_augmented_kernel`: the run's dict and the four parameters at the
    recorded stamps, (n, 4)."""
    ka = _jit_kernels_augmented.pure_module() if (JIT and not jit) else _jit_kernels_augmented
    aug = augment_of(spec)
    theta = np.full((n, 4), np.nan)
    diverged, j, nis_sum, n_updates, n_rejected = ka.run_augmented_kernel(
        *_common_args(ctx, run),
        np.array(aug.estimated(), dtype=np.int64), np.array(aug.start, dtype=float),
        np.array(aug.sigma0, dtype=float), np.array(aug.drift, dtype=float),
        _jit_kernels_augmented.rule_params(spec), run[-1], x, P, R, Qu, theta,
    )  # fmt: skip
    if diverged:
        theta[j:] = np.nan
    return _result(x, P, R, Qu, n, diverged, j, nis_sum, n_updates, n_rejected), theta


def augmented_run(spec: FilterSpec, ctx: FilterContext, tl: Timeline, *, jit: bool = True):
    """`run_filter_fast` of an `ekf-aug` (or a family's `augment:`) and its parameter estimates
    at the recorded stamps (n, 4: speed scale, turn scale, turn bias, range bias)."""
    motion = _motion(ctx.model)
    if motion is None:
        raise ValueError(f"the fast engine does not implement {type(ctx.model)}")
    run = _run_args(tl, motion)
    n = int(np.count_nonzero(tl.record))
    x, P = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    R, Qu = np.full((n, 2), np.nan), np.full((n, 2), np.nan)
    return run_augmented(spec, ctx, run, x, P, R, Qu, n, jit)


def _run_augmented(spec: FilterSpec, ctx: FilterContext, run: tuple, x, P, R, Qu, n, jit):
    """`run_augmented`'s run dict, without the parameters' records."""
    return run_augmented(spec, ctx, run, x, P, R, Qu, n, jit)[0]


# The kernels of their own by the module a spec class names (`FilterSpec.fast_kernel`), each
# called as (spec, ctx, run, x, P, R, Qu, n, jit) -> the run's dict.
KERNEL_RUNNERS = {
    "kernels_bank": _run_bank, "kernels_swvb": _run_swvb, "kernels_als": _run_als,
    "kernels_kalmannet": _run_kalmannet, "kernels_augmented": _run_augmented,
}  # fmt: skip


def _bank_args(kb, spec: MMAESpec, ctx: FilterContext) -> tuple:
    """`kernels_bank.run_bank_kernel`'s arguments between the run's and the records' for
    filters.bank.BankEKF: members that hold their R hypothesis, the Gaussian likelihood."""
    factors = hypotheses(spec)
    Qu_m = np.ascontiguousarray(factors[:, :2] * np.diag(ctx.Qu))
    R_m = np.ascontiguousarray(factors[:, 2:] * np.diag(ctx.R))
    has_gate = ctx.gate is not None
    censor_at = ctx.gate if (spec.adapt_from == "accepted" and has_gate) else math.inf
    imm = isinstance(spec, IMMSpec)
    return (
        np.ascontiguousarray(ctx.x0, dtype=float).reshape(3), _matrix(ctx.P0, 3),
        Qu_m, R_m, _matrix(ctx.R, 2), float(ctx.gate) if has_gate else math.inf, has_gate,
        kb.RULE_GRID, False, 1.0, 1.0, 1.0, 0, 1.0, 1.0,  # no R rule: its settings unused
        float(censor_at), math.inf, math.log(spec.weight_floor), float(spec.mixture_threshold),
        imm, float(spec.p_stay) if imm else 1.0,
    )  # fmt: skip


def _vb_imm_args(kb, spec: VBIMMSpec, ctx: FilterContext) -> tuple:
    """`kernels_bank.run_bank_kernel`'s arguments between the run's and the records' for
    filters.vb_bank.VBIMMEKF: members that adapt R by `spec.r_rule` (or hold it: grid)."""
    factors = member_factors(spec)
    Qu_m = np.ascontiguousarray(np.outer(factors[:, 0], np.diag(ctx.Qu)))
    R_m = np.ascontiguousarray(factors[:, 1:] * np.diag(ctx.R))
    has_gate = ctx.gate is not None
    censor_at = ctx.gate if (spec.adapt_from == "accepted" and has_gate) else math.inf
    rule = R_RULE_CODE[spec.r_rule] if spec.adaptation else R_RULE_CODE["grid"]
    p_stay = float(spec.p_stay) if spec.adaptation else 1.0
    return (
        np.ascontiguousarray(ctx.x0, dtype=float).reshape(3), _matrix(ctx.P0, 3),
        Qu_m, R_m, _matrix(ctx.R, 2), float(ctx.gate) if has_gate else math.inf, has_gate,
        rule, spec.adapt_from == "all", float(spec.bounds[0]), float(spec.bounds[1]),
        float(spec.rho), int(spec.iterations), float(spec.alpha0), float(spec.b),
        float(censor_at), float(spec.likelihood_dof), math.log(spec.weight_floor),
        float(spec.mixture_threshold), p_stay < 1.0 and len(factors) > 1, p_stay,
    )  # fmt: skip


# The kernels `warm_up` calls directly besides the families' loops (their callees compile, and
# are cached, with them).
WARM_UP_KERNELS = (
    (_jit_kernels_swvb, "run_swvb_kernel"),
    (_jit_kernels_als, "run_als_kernel"),
    (_jit_kernels_kalmannet, "run_kalmannet_kernel"),
    (_jit_kernels_augmented, "run_augmented_kernel"),
    (_jit_kernels_bank, "run_bank_kernel"),
    (_run_means, "time_means"),
    (_metrics, "trace_metrics"),
)  # fmt: skip
COMPILE_ESTIMATE = "a few minutes"  # one process: about 4 min of CPU (lead, 2026-11-27, load 12)


def kernels_cached() -> bool | None:
    """Whether numba's on-disk cache holds every kernel `warm_up` compiles, valid for this
    source (numba checks the file's stamp): False means the first fast run compiles them (a
    minute or two); None when the kernels are not compiled (no numba) or the cache cannot be
    inspected (numba's FunctionCache API changed: say nothing rather than something wrong)."""
    if not JIT:
        return None
    try:
        loops = [_loop.compiled_loop(families.for_spec(s)) for s in warm_up_specs("loop")]
        kernels = [getattr(module, name) for module, name in WARM_UP_KERNELS]
        return all(bool(k._cache._cache_file._load_index()) for k in loops + kernels)
    except Exception:  # a private numba API: any change means "unknown"
        return None


# `make setup` compiles the warm-up in two processes side by side (numba compiles on one core):
# "loop", every family's loop (`loop.compiled_loop`; the Makefile then compiles the problems'
# loops in that process), and "kernels", the kernels of their own, the fits' kernels and the
# simulator's truth loop (about 70 s each, 2026-11-28).
WARM_UP_PARTS = ("loop", "kernels")


def warm_up_specs(part: str | None = None) -> tuple[FilterSpec, ...]:
    """One filter of every kernel: each family module on the one loop (it compiles a loop of its
    own; the first registered kind that names it, with its defaults) and each kind with a kernel
    of its own; the kinds left out share one of these (tests/test_fast_engine.py checks).
    `part` (WARM_UP_PARTS): the loop's families only, or the kernels of their own only."""
    loop_specs: dict[str, FilterSpec] = {}
    for cls in REGISTERED_SPECS:
        name = fast_family_of(cls)
        if name is not None and name not in loop_specs and not cls.fitted_on_training:
            kind = kind_of(cls)
            loop_specs[name] = cls.model_validate({"name": kind, "kind": kind})
    if part == "loop":
        return tuple(loop_specs.values())
    return (
        *(loop_specs.values() if part is None else ()),
        SWVBSpec(name="swvb", kind="swvb"), ALSSpec(name="als", kind="als"),
        MMAESpec(name="mmae", kind="mmae"), IMMSpec(name="imm", kind="imm"),
        VBIMMSpec(name="vb-imm", kind="vb-imm"),
        AugmentedSpec(name="ekf-aug", kind="ekf-aug", estimate=list(PARAMETERS)),
        KalmanNetSpec.model_construct(name="kalmannet", kind="kalmannet").with_weights(
            KalmanNetWeights.random(hidden_size=4)
        ),
    )  # fmt: skip


def warm_up(jit: bool = True, part: str | None = None) -> float:
    """Compile (or load from numba's cache) every kernel signature the engine uses by running
    a tiny EKF, ANFEKF (and cm-scale: the same kernel), akhlaghi, vb-r, vbakf, swvb, Sage-Husa,
    IAE, ALS and KalmanNet (a small random network); returns the seconds it took. `part`
    (WARM_UP_PARTS): the loop's families only, or the rest only (`make setup` runs both parts
    side by side)."""
    import time

    from ..sources.simulator import Scan, Truth, simulate_truth

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
    for spec in warm_up_specs(part):
        run_filter_fast(spec, ctx, data, world, 1, jit=jit)
    clear_cache()
    if part == "loop":
        return time.perf_counter() - t0
    # The fits' kernel (ekf-ml, ekf-tuned and the recorded data's grid searches): one likelihood
    # pass compiles it and its step table; without it a first fitted run compiled them.
    from ..timeline import from_run
    from .tuning import GridRuns, TimelineLikelihood

    tl = from_run(data, world, 0)
    likelihood = TimelineLikelihood.of(tl, ctx.x0, ctx.P0, ctx.gate, 0.0)
    likelihood.nll(np.array([0.3, 0.05, 0.1, 0.02]))
    n_rec = int(tl.record.sum())  # and the recorded data's grid searches (one grid call)
    GridRuns.of([(tl, ctx.x0, np.zeros((n_rec, 3)), np.ones(n_rec, bool))]).score(
        np.array([[0.3, 0.05, 0.1, 0.02]]), ctx.P0, ctx.gate, world.T
    )
    simulate_truth(dataclasses.replace(world, max_steps=10_000))  # the simulator's truth loop
    block = np.ones((1, 2))  # the tables' bootstrap (statistics._resampled_by_weights)
    _run_means.time_means(block, block, True, True, np.empty(1))
    x3, P3, out = np.zeros((1, 3)), np.eye(3)[None], np.empty(1)  # a fast run's metrics
    _metrics.trace_metrics(x3, x3, P3, out, out.copy(), out.copy())
    return time.perf_counter() - t0


def _tiny_world() -> World:
    return World(
        landmarks=np.array([[10.0, 1.0]]), waypoints=np.array([[20.0, 0.0]]), loops=1,
        x0=np.zeros(3), V=3.0, B=4.0, max_steer=0.5, max_steer_rate=0.35, T=0.025,
        sensor_every=8, max_range=20.0, half_fov=math.pi / 2, waypoint_tolerance=1.0,
        max_steps=100,
    )  # fmt: skip


def serialise_cache_writes() -> bool:
    """Make numba's cache writes in this process take an exclusive lock on the cache folder
    (fcntl), so that warm-up processes running side by side never lose or mix up each other's
    entries: numba reads a function's index, adds its entry and writes it back, unlocked, and
    numbers the entry's data file by what it read (two processes compiling the same callee for
    different signatures would both write data file 1). False without fcntl (not POSIX) or when
    numba's cache class is not the one this wraps (then the parts run one after the other)."""
    import os
    import tempfile

    try:
        import fcntl  # POSIX only: elsewhere the parts run one after the other

        from numba.core.caching import IndexDataCacheFile

        save = IndexDataCacheFile.save
    except (ImportError, AttributeError):
        return False
    if getattr(save, "serialised", False):
        return True

    def locked_save(self, key, data):
        folder = getattr(self, "_cache_path", None) or tempfile.gettempdir()
        with open(os.path.join(folder, ".anfekf-warm-up.lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            save(self, key, data)

    locked_save.serialised = True
    IndexDataCacheFile.save = locked_save
    return True


if __name__ == "__main__":  # `make setup`: compile every kernel into numba's cache, once
    import sys

    usage = "usage: python -m anfekf_bench.engines.fast --warm-up [--part loop|kernels]"
    args = sys.argv[1:]
    if args[:1] != ["--warm-up"] or args[1:] not in ([], *(["--part", p] for p in WARM_UP_PARTS)):
        sys.exit(usage)
    if not JIT:
        print("numba is not installed (or ANFEKF_FAST_JIT=0): nothing to compile")
        sys.exit(0)
    part = args[2] if len(args) == 3 else None
    if part is not None and not serialise_cache_writes():
        # numba's cache is not the one serialise_cache_writes wraps: compile every part in the
        # "loop" process, one after the other, and nothing in the other
        if part == "kernels":
            sys.exit(0)
        part = None
    seconds = warm_up(part=part)
    what = f"numba kernels ({part or 'all'})"
    print(f"fast engine: {what} compiled into the cache in {seconds:.0f} s")
