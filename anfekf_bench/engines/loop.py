"""The fast engine's one loop: a filter family's run as the EKF's stamps with the family's hooks.

Every family that runs as one EKF (one state, one P) shares this loop: per stamp the predict,
per landmark of the stamp's scan the innovation, the family's `before_gain`, the NIS and the
gate, the Joseph update; at the end of the scan the family's `end_scan` and the health check;
then the record. The family's per-event steps are plain numeric functions in its module under
`engines/families/` (`start`, `predicted`, `begin_scan`, `before_gain`, `rejected`,
`corrected`, `end_scan`, `inflation`: the protocol below), called on the family's parameters
`fam` (a namedtuple of the module, `Params`) and its state `st` (a tuple the hooks return anew).

How the loop reaches a family's hooks (docs/DESIGN.md, "One loop, one module per family"): each
hook name here is a stub that, compiled, numba resolves by the TYPE of `fam` (`overload`: the
namedtuple's class names its module, whose function of that name is inlined into the loop's
numba IR: numba then prunes the reference counts of the state passing through it), so
`run_loop` is compiled once per family, as one kernel per family was, and numba's disk cache
keeps every specialisation (a loop that took the hooks as function arguments would be compiled
again in every process: numba does not cache such signatures). Run as plain Python (no numba, or
`pure_module()`), the stubs call the same functions by the same lookup.

numba's disk cache is keyed on THIS file's contents: after editing a family's hooks, delete
__pycache__/loop.*.nbi so that the loop is compiled again (the equivalence tests fail on a
stale cache).
"""

from __future__ import annotations

import math
import sys

from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT
maybe_njit = _k.maybe_njit
jacobians, noise_scale, predict_with = _k.jacobians, _k.noise_scale, _k.predict_with
innovation, nis, correct, healthy, record = (
    _k.innovation, _k.nis, _k.correct, _k.healthy, _k.record,
)  # fmt: skip

# The hooks, in the order the loop calls them, with what they receive and return:
#   start(fam, x, P, Qu, R, scan_start) -> st
#   predicted(fam, st, f02, f12, G, c, Q) -> st          after each predict (Jacobians, Q)
#   begin_scan(fam, st, x, P, R, Qu) -> (st, R)           a stamp with landmarks
#   before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate)
#       -> (ok, st, P, R, Qu, HPHt)                       per landmark, before its NIS and gain
#   rejected(fam, st, x, P, R, H, zh, lm, z) -> (ok, st, P, R)      the gate rejected it
#   corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z) -> (st, R)   after its update
#   end_scan(fam, st, x, P, R, Qu) -> (ok, st, R, Qu)
#   inflation(fam, st) -> float                           what P_infl records (1: none)
# Before the loop (in Python, not a hook): a family module's optional for_run(fam, scan_start)
# -> fam sizes arrays of `fam` by the run (engines/fast.py calls it). Arrays a family updates in
# place belong in `fam`, not in `st`: the state passes through the hooks (reference counts).
# ok False: the filter diverged (a singular matrix, a value that is not finite). A hook the
# family's module does not define is the default below: no state, nothing changes, no inflation.


def _start(fam, x, P, Qu, R, scan_start):
    return 0


def _predicted(fam, st, f02, f12, G, c, Q):
    return st


def _begin_scan(fam, st, x, P, R, Qu):
    return st, R


def _before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    return True, st, P, R, Qu, HPHt


def _rejected(fam, st, x, P, R, H, zh, lm, z):
    return True, st, P, R


def _corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z):
    return st, R


def _end_scan(fam, st, x, P, R, Qu):
    return True, st, R, Qu


def _inflation(fam, st):
    return 1.0


DEFAULTS = {
    "start": _start, "predicted": _predicted, "begin_scan": _begin_scan,
    "before_gain": _before_gain, "rejected": _rejected, "corrected": _corrected,
    "end_scan": _end_scan, "inflation": _inflation,
}  # fmt: skip
HOOKS = tuple(DEFAULTS)


# numba IR inlining of the hooks ("never": LLVM's inlining of a call, which leaves the reference
# counts of a state with arrays; the families on the loop took 1.1-1.3 times their former
# kernels' time per step that way, docs/DESIGN.md)
INLINE = "always"


def family_of(fam):
    """The module holding the hooks of parameters `fam` (its namedtuple's module)."""
    return sys.modules[type(fam).__module__]


_REGISTERED: set = set()
# A family's own functions compile as the kernels do (kernels.maybe_njit): numpy's error model
# (a division by zero gives inf or NaN, no check for it), which the hand-written kernels had.
JIT_OPTIONS = {"error_model": "numpy"}


def _hook(module, name: str):
    """The hook `name` of a family module (or the default), every function the module defines
    registered with numba first (once), so that compiled code calls the hooks and their
    helpers."""
    import inspect

    from numba.extending import register_jitable

    if not _REGISTERED:
        for fn in DEFAULTS.values():
            register_jitable(**JIT_OPTIONS)(fn)
        _REGISTERED.add(__name__)
    if module.__name__ not in _REGISTERED:
        for fn in vars(module).values():
            if inspect.isfunction(fn) and fn.__module__ == module.__name__:
                register_jitable(**JIT_OPTIONS)(fn)
        _REGISTERED.add(module.__name__)
    return getattr(module, name, DEFAULTS[name])


def _stub(name: str):
    """The stub of hook `name`: its default's arguments spelt out (numba inlines an overload
    into the loop's IR only for a function without `*args`), calling the family's hook."""
    import inspect

    params = ", ".join(inspect.signature(DEFAULTS[name]).parameters)
    src = (
        f"def {name}({params}):\n"
        f"    return getattr(family_of(fam), {name!r}, DEFAULTS[{name!r}])({params})\n"
    )
    scope = {"family_of": family_of, "DEFAULTS": DEFAULTS}
    exec(src, scope)
    stub = scope[name]
    stub.__doc__ = f"The family's `{name}` hook (resolved by the type of `fam`)."
    if JIT and not _PURE_COPY:
        from numba.extending import overload

        def _resolve(*types):
            hook = _hook(sys.modules[types[0].instance_class.__module__], name)
            return hook

        typing: dict = {"_resolve": _resolve}  # the typer: the stub's signature, spelt out
        exec(f"def typer({params}):\n    return _resolve({params})\n", typing)
        overload(stub, inline=INLINE)(typing["typer"])

    return stub


start, predicted, begin_scan, before_gain, rejected, corrected, end_scan, inflation = (
    _stub(name) for name in HOOKS
)


@maybe_njit
def run_loop(
    fam, u_odo, dt, scan_start, scan_lm, scan_z, motion, B, T0, x0, P0, Qu0, R0, gate, has_gate,
    record_at, out_x, out_P, out_R, out_Q, out_infl,
):  # fmt: skip
    """One filter of family `fam` over one run (filterpy_engine.run_filter with its class).

    The run is a `timeline.Timeline` (kernels.run_kernel's arguments): stamp k predicts with
    u_odo[k] over dt[k] on `motion`, then runs its landmarks scan_start[k] .. scan_start[k + 1]
    - 1 of scan_lm (map positions) and scan_z as one scan, then records if record_at[k]. x0 (3,),
    P0 (9,), Qu0 (4,), R0 (4,) row-major. A recorded stamp is row j of out_x (n, 3), out_P
    (n, 3, 3), out_R (n, 2), out_Q (n, 2) and out_infl (n,); rows from a divergence on are left
    as they are. Returns (diverged, rows written, nis_sum, n_updates, n_rejected).
    """
    K = u_odo.shape[0]
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qu = (Qu0[0], Qu0[1], Qu0[2], Qu0[3])
    R = (R0[0], R0[1], R0[2], R0[3])
    st = start(fam, x, P, Qu, R, scan_start)
    nis_sum = 0.0
    n_updates = 0
    n_rejected = 0
    n_rows = out_x.shape[0]
    j = 0
    bad_record = False
    for k in range(K):
        u0 = u_odo[k, 0]
        u1 = u_odo[k, 1]
        dt_k = dt[k]
        f02, f12, G = jacobians(x[2], u0, u1, dt_k, motion, B)
        x, P, Q = predict_with(x, P, f02, f12, G, u0, u1, dt_k, motion, B, T0, Qu)
        st = predicted(fam, st, f02, f12, G, noise_scale(dt_k, motion, T0), Q)
        first = scan_start[k]  # this stamp's landmarks first .. last - 1: one scan
        last = scan_start[k + 1]
        if last > first:
            st, R = begin_scan(fam, st, x, P, R, Qu)
            for m in range(first, last):
                lm = (scan_lm[m, 0], scan_lm[m, 1])
                z = (scan_z[m, 0], scan_z[m, 1])
                H, zh, nu, HPHt = innovation(x, P, lm[0], lm[1], z[0], z[1])
                ok, st, P, R, Qu, HPHt = before_gain(
                    fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate
                )
                if not ok:
                    return True, j, nis_sum, n_updates, n_rejected
                # RobotEKF.update_landmark: NIS, gate, Joseph update
                ok, v = nis(HPHt, R, nu[0], nu[1])
                if not ok or not math.isfinite(v):
                    return True, j, nis_sum, n_updates, n_rejected
                if has_gate and not v <= gate:
                    n_rejected += 1
                    ok, st, P, R = rejected(fam, st, x, P, R, H, zh, lm, z)
                    if not ok:
                        return True, j, nis_sum, n_updates, n_rejected
                    continue
                nis_sum += v
                n_updates += 1
                x_prior = x
                P_prior = P
                ok, x, P = correct(x, P, H, zh, z[0], z[1], R)
                if not ok:
                    return True, j, nis_sum, n_updates, n_rejected
                st, R = corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z)
            ok, st, R, Qu = end_scan(fam, st, x, P, R, Qu)
            if not ok or not healthy(x, P, R, Qu):
                return True, j, nis_sum, n_updates, n_rejected
        if record_at[k] and j < n_rows:
            out_infl[j] = inflation(fam, st)
            j, bad = record(j, x, P, R, Qu, out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    # health is checked at scans; a blow-up after the last one shows in the records
    return bad_record, j, nis_sum, n_updates, n_rejected


def pure_module():
    """A fresh copy of this module whose loop is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)
