"""numba where it is installed and not switched off: the one switch for compiled code. The fast
engine's kernels (engines.kernels, which adds its plain-Python copy), the simulator's truth loop
and the bootstrap's time means (analysis.run_means) all compile through it.

Set the environment variable ANFEKF_FAST_JIT=0 to keep numba off even when it is installed.
"""

from __future__ import annotations

import os

# numba's cache keeps one entry per function and signature, whatever the options: one set for
# every compiled function. nogil: the callers run on threads.
NJIT_OPTIONS = {"cache": True, "nogil": True, "error_model": "numpy"}


def numba_njit():
    """numba.njit, or None when numba is missing or switched off (ANFEKF_FAST_JIT=0)."""
    if os.environ.get("ANFEKF_FAST_JIT", "1") == "0":
        return None
    try:
        import numba
    except ImportError:
        return None
    return numba.njit


def maybe_njit(fn):
    """`fn` compiled with `NJIT_OPTIONS` when numba is in use, else the function itself."""
    njit = numba_njit()
    return fn if njit is None else njit(**NJIT_OPTIONS)(fn)


def is_compiled(fn) -> bool:
    """Whether `maybe_njit` compiled `fn` (a numba dispatcher keeps the Python function)."""
    return hasattr(fn, "py_func")
