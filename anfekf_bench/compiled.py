"""numba where it is installed and not switched off, for the compiled code outside the fast
engine's kernels (engines.kernels keeps a switch of its own, with its plain-Python copy): the
simulator's truth loop and the bootstrap's time means (analysis.run_means).

Set the environment variable ANFEKF_FAST_JIT=0 to keep numba off even when it is installed.
"""

from __future__ import annotations

import os


def maybe_njit(fn):
    """`numba.njit(cache=True)` when numba is installed and not switched off, else the function
    itself. The options are the fast engine's (engines.kernels.maybe_njit): numba's cache keeps
    one entry per function and signature, whatever the options. nogil: the callers run on
    threads."""
    if os.environ.get("ANFEKF_FAST_JIT", "1") == "0":
        return fn
    try:
        import numba
    except ImportError:
        return fn
    return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)


def is_compiled(fn) -> bool:
    """Whether `maybe_njit` compiled `fn` (a numba dispatcher keeps the Python function)."""
    return hasattr(fn, "py_func")
