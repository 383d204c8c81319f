"""The fast engine's one loop: a filter family's run as the EKF's stamps with the family's hooks.

Every family that runs as one EKF (one state, one P) shares this loop: per stamp the predict,
per landmark of the stamp's scan the innovation, the family's `before_gain`, the NIS and the
gate, the Joseph update; at the end of the scan the family's `end_scan` and the health check;
then the record. The family's per-event steps are plain numeric functions in its module under
`engines/families/` (`start`, `predicted`, `begin_scan`, `before_gain`, `rejected`,
`corrected`, `end_scan`, `inflation`: the protocol below), called on the family's parameters
`fam` (a namedtuple of the module, `Params`) and its state `st` (a tuple the hooks return anew).

How the loop reaches a family's hooks (docs/DESIGN.md, "One loop, one module per family"):
run as plain Python (no numba, or `pure_module()`), each hook name here is a stub that calls the
function of that name in the module of `fam`'s class. Compiled, `compiled_loop(module)` writes
`run_loop`'s source into a module of its own with the family's hooks bound to those names as
numba functions that numba inlines into the loop's IR (`inline_hook`); numba compiles that
module's `run_loop` once per family and caches it on disk like any kernel (a loop that took the
hooks as function arguments would be compiled again in every process: numba does not cache such
signatures). The generated file's name carries a digest of every source the loop reaches, so an
edit of a family's hooks or of a rule they call compiles its loop anew.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
from pathlib import Path

from ..compiled import reached_modules, unchanged_source_stat
from ..storage import write_new
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT
maybe_njit = _k.maybe_njit
jacobians, noise_scale, predict_with = _k.jacobians, _k.noise_scale, _k.predict_with
innovation, nis, correct, healthy, record = (
    _k.innovation, _k.nis, _k.correct, _k.healthy, _k.record,
)  # fmt: skip
stamp_input, NO_TALLY = _k.stamp_input, _k.NO_TALLY

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


def family_of(fam):
    """The module holding the hooks of parameters `fam` (its namedtuple's module)."""
    return sys.modules[type(fam).__module__]


_REGISTERED: set = set()
# A family's own functions compile as the kernels do (kernels.maybe_njit): numpy's error model
# (a division by zero gives inf or NaN, no check for it), which the hand-written kernels had.
JIT_OPTIONS = {"error_model": "numpy"}


def _register(module) -> None:
    """Register every function `module` defines with numba (once), so that compiled code can
    call the family's helpers (its hooks are inlined: `inline_hook`)."""
    import inspect

    from numba.extending import register_jitable

    if module.__name__ not in _REGISTERED:
        for fn in vars(module).values():
            if inspect.isfunction(fn) and fn.__module__ == module.__name__:
                register_jitable(**JIT_OPTIONS)(fn)
        _REGISTERED.add(module.__name__)


_INLINE_HOOKS: dict = {}


def inline_hook(module, name: str):
    """The hook `name` of family `module` (or the default) as a numba function that numba
    inlines into its caller's IR before typing it (`inline="always"`): typed once, in the loop,
    where numba prunes the reference counts of the state passing through it."""
    key = (module.__name__, name)
    if key not in _INLINE_HOOKS:
        from numba import njit

        _register(module)
        hook = getattr(module, name, DEFAULTS[name])
        _INLINE_HOOKS[key] = njit(inline="always", **JIT_OPTIONS)(hook)
    return _INLINE_HOOKS[key]


def _stub(name: str):
    """The hook `name` of the family that defines `fam` (run as plain Python)."""

    def stub(fam, *args):
        return getattr(family_of(fam), name, DEFAULTS[name])(fam, *args)

    stub.__name__ = stub.__qualname__ = name
    stub.__doc__ = f"The family's `{name}` hook (resolved by the module of `fam`'s class)."
    return stub


start, predicted, begin_scan, before_gain, rejected, corrected, end_scan, inflation = (
    _stub(name) for name in HOOKS
)


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
    bad_record, j, nis_sum, n_updates, n_rejected = NO_TALLY
    n_rows = out_x.shape[0]
    for k in range(K):
        u0, u1, dt_k = stamp_input(u_odo, dt, k)
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


# The compiled loop of a family: run_loop's source above, written with the family's hooks into a
# module of its own (`_loop_source`), which numba compiles and caches on disk like any kernel.
# One module per family, not one `run_loop` specialised by the type of `fam` through `overload`
# stubs (the way before): numba compiles an overload's implementation whole before inlining it
# and compiles the hooks' callees a second time under the loop's flags, so that way took about
# 1.35 times as long to compile, for the same machine code (docs/DESIGN.md, "One loop, one
# module per family").
_COMPILED: dict = {}


_GENERATING = threading.Lock()  # runs on threads may ask for the same family's loop at once


def compiled_loop(module):
    """`run_loop` for family `module`: numba-compiled (and cached) when numba is in use, else
    this module's plain-Python `run_loop`."""
    if not JIT or _PURE_COPY:
        return run_loop
    with _GENERATING:
        if module.__name__ not in _COMPILED:
            _COMPILED[module.__name__] = _generated_module(module).run_loop
    return _COMPILED[module.__name__]


def _loop_source(module) -> str:
    """The source of the module that compiles `run_loop` for family `module`."""
    import inspect

    code = run_loop.__code__
    names = [n for n in code.co_names if n in globals() and n not in HOOKS]
    return (
        f"# Generated by {__name__}.compiled_loop from its run_loop, for the family\n"
        f"# {module.__name__}; not to be edited (written anew under another name when a\n"
        "# source it reaches changes).\n"
        "import importlib\n\n"
        f"from {__name__} import HOOKS, inline_hook, maybe_njit\n"
        f"from {__name__} import {', '.join(names)}  # noqa: F401\n\n"
        f"_family = importlib.import_module({module.__name__!r})\n"
        f"{', '.join(HOOKS)} = (inline_hook(_family, name) for name in HOOKS)\n\n\n"
        f"@maybe_njit\n{inspect.getsource(run_loop)}"
    )


def _generated_module(module):
    """Import (writing it first if need be) the module of `_loop_source(module)`. Its file's
    name carries a digest of its text and of the sources of every module the loop can reach
    (`compiled.reached_modules`: the family's, the kernels, the filters' rules), so that an edit
    of any of them compiles anew; the file is never rewritten (numba's cache is keyed on it)."""
    import hashlib
    import importlib.util

    text = _loop_source(module)
    digest = hashlib.sha256(text.encode())
    for reached in reached_modules(module, sys.modules[__name__]):
        source = Path(reached.__file__).resolve()
        if unchanged_source_stat(str(source)) is None:
            # this process runs the code it imported, the digest would name the edited file's:
            # the cache would hand the old code to every later process
            raise RuntimeError(
                f"{source} changed after this process imported it: start a new process to run"
                " the fast engine on the edited code"
            )
        digest.update(source.read_bytes())
    name = f"{module.__name__.rsplit('.', 1)[-1]}_{digest.hexdigest()[:16]}"
    path = _generated_folder() / f"loop_{name}.py"
    if not path.is_file():
        # created once, exclusively (storage.write_new): a process writing it beside another
        # never changes the file the other's numba cache recorded
        with contextlib.suppress(FileExistsError):
            write_new(path, text.encode())
    spec = importlib.util.spec_from_file_location(f"{__name__}_{name}", path)
    generated = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = generated
    # the text made here, not what the file holds now: the file only names the code for numba
    exec(compile(text, str(path), "exec"), generated.__dict__)
    return generated


def _generated_folder():
    """Where the generated loops go: beside numba's cache when NUMBA_CACHE_DIR names one, else
    this package's __pycache__ (numba's cache of them goes beside them), else the user's
    cache folder (a read-only install)."""
    import os

    from numba.core.config import CACHE_DIR

    folders = [Path(CACHE_DIR) / "anfekf_loops"] if CACHE_DIR else []
    folders += [Path(__file__).parent / "__pycache__" / "loops", "~/.cache/anfekf-bench/loops"]
    tried = []
    for folder in folders:
        try:
            folder = Path(folder).expanduser()  # no home folder: RuntimeError, next
            folder.mkdir(parents=True, exist_ok=True)
        except (OSError, RuntimeError):
            tried.append(str(folder))
            continue
        if os.access(folder, os.W_OK):
            return folder
        tried.append(str(folder))
    raise OSError(
        f"no writable folder for the fast engine's compiled loops (tried {', '.join(tried)});"
        " set NUMBA_CACHE_DIR to one"
    )


def pure_module():
    """A fresh copy of this module whose loop is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)
