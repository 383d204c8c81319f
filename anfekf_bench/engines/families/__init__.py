"""The families of the fast engine's loop (`engines/loop.py`), one module each: its `Params`,
the spec classes it runs (`SPECS`), `params(spec, ctx)` and its hooks (loop.HOOKS).

MODULES is the one list the fast engine reads (docs/DESIGN.md, "One loop, one module per
family"); a kind whose spec class no module lists, but that the fast engine supports through
the loop, is the plain EKF (a recorded scenario's ekf-tuned): the first module's.
"""

from __future__ import annotations

import importlib

from .. import kernels as _kernels

MODULES = (
    "anfekf_bench.engines.families.anfekf",
    "anfekf_bench.engines.families.fading",
    "anfekf_bench.engines.families.vb_r",
    "anfekf_bench.engines.families.sage_husa",
    "anfekf_bench.engines.families.iae",
    "anfekf_bench.engines.families.akhlaghi",
    "anfekf_bench.engines.families.vbakf",
)


def modules(pure: bool = False) -> tuple:
    """The family modules (pure: their plain-Python copies)."""
    mods = tuple(importlib.import_module(name) for name in MODULES)
    if pure:
        mods = tuple(_kernels.pure_copy(m.__name__, m.__file__) for m in mods)
    return mods


def for_spec(spec, pure: bool = False):
    """The family module that lists `spec`'s class (exactly), or None."""
    for mod in modules(pure):
        if type(spec) in mod.SPECS:
            return mod
    return None
