"""Which filters the fast engine runs, without importing it (numba, its kernels).

`anfekf kinds` lists each kind's engines: registering this light check costs a fraction of a
second, where importing `engines.fast` (which registers its full `supports`, motion models
included) compiles nothing but imports numba and every kernel module."""

from __future__ import annotations

import sys

from ..filters.als import ALSSpec
from ..filters.augmented import AugmentedSpec, CalibratedAugmentedSpec
from ..filters.bank import IMMSpec, MMAESpec
from ..filters.kalmannet import KalmanNetSpec
from ..filters.registry import SPECS, register_engine
from ..filters.spec import FilterSpec, fast_family_of
from ..filters.swvb import SWVBSpec
from ..filters.vb_bank import VBIMMSpec

# The kinds with a kernel of their own (exactly these classes: a subclass may build a different
# filter); a kind on the one loop names its family module on its spec class instead
# (`FilterSpec.fast_family`: the EKF and its fitted and oracle forms, a recorded scenario's
# ekf-tuned, the adaptive families of engines/families).
OWN_KERNEL_SPECS: tuple[type[FilterSpec], ...] = (
    MMAESpec, IMMSpec, SWVBSpec, ALSSpec, KalmanNetSpec, AugmentedSpec, CalibratedAugmentedSpec,
    VBIMMSpec,
)  # fmt: skip
# Every registered spec class the fast engine runs (for tests and docs; `supported_type` decides).
SUPPORTED_SPECS: tuple[type[FilterSpec], ...] = tuple(
    cls for cls in SPECS if cls in OWN_KERNEL_SPECS or fast_family_of(cls) is not None
)


def supported_type(spec: FilterSpec) -> bool:
    """Whether the fast engine implements this spec's filter (on some motion model)."""
    return fast_family_of(spec) is not None or type(spec) in OWN_KERNEL_SPECS


def register() -> None:
    """Register the fast engine's kinds with the registry (for `anfekf kinds`); importing
    `engines.fast` registers its own `supports` in its place (kept, if it is loaded)."""
    if "anfekf_bench.engines.fast" not in sys.modules:
        register_engine("fast", supported_type)
