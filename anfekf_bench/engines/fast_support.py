"""Which filters the fast engine runs, without importing it (numba, its kernels).

`anfekf kinds` lists each kind's engines: registering this light check costs a fraction of a
second, where importing `engines.fast` (which registers its full `supports`, motion models
included) compiles nothing but imports numba and every kernel module."""

from __future__ import annotations

import sys

from ..filters.registry import SPECS, register_engine
from ..filters.spec import FilterSpec, fast_family_of, fast_kernel_of

# Every registered spec class the fast engine runs (for tests and docs; `supported_type` decides).
SUPPORTED_SPECS: tuple[type[FilterSpec], ...] = tuple(
    cls for cls in SPECS if fast_family_of(cls) is not None or fast_kernel_of(cls) is not None
)


def supported_type(spec: FilterSpec | type[FilterSpec]) -> bool:
    """Whether the fast engine implements this spec's filter (on some motion model): its class
    names a family module on the one loop (`FilterSpec.fast_family`: the EKF and its fitted
    and oracle forms, the adaptive families of engines/families) or a kernel of its own
    (`FilterSpec.fast_kernel`: the banks, swvb, als, kalmannet, the augmented EKFs)."""
    return fast_family_of(spec) is not None or fast_kernel_of(spec) is not None


def register() -> None:
    """Register the fast engine's kinds with the registry (for `anfekf kinds`); importing
    `engines.fast` registers its own `supports` in its place (kept, if it is loaded)."""
    if "anfekf_bench.engines.fast" not in sys.modules:
        register_engine("fast", supported_type)
