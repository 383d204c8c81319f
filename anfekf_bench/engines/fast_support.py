"""Which filters the fast engine runs, without importing it (numba, its kernels).

`anfekf kinds` lists each kind's engines: registering this light check costs a fraction of a
second, where importing `engines.fast` (which registers its full `supports`, motion models
included) compiles nothing but imports numba and every kernel module."""

from __future__ import annotations

import sys

from ..filters.akhlaghi import AkhlaghiSpec
from ..filters.als import ALSSpec
from ..filters.anfekf import ANFEKFSpec
from ..filters.augmented import AugmentedSpec
from ..filters.bank import IMMSpec, MMAESpec
from ..filters.cm_scale import CMScaleSpec
from ..filters.ekf import EKFSpec, OracleSpec
from ..filters.fading import FadingSpec
from ..filters.fitted import EKFMLSpec, EKFTunedSpec
from ..filters.iae import IAESpec
from ..filters.kalmannet import KalmanNetSpec
from ..filters.registry import register_engine
from ..filters.sage_husa import SageHusaSpec
from ..filters.spec import FilterSpec
from ..filters.swvb import SWVBSpec
from ..filters.vb import VBAKFSpec, VBRSpec
from ..filters.vb_bank import VBIMMSpec

# Exactly these spec classes (a subclass may build a different filter).
# ekf-ml and ekf-tuned are the plain EKF with fitted noise (filters.fitted; a recorded
# scenario's ekf-tuned, sources.recorded.TunedEKFSpec, with grid-searched noise).
SUPPORTED_SPECS: tuple[type[FilterSpec], ...] = (
    EKFSpec, OracleSpec, ANFEKFSpec, EKFMLSpec, EKFTunedSpec, MMAESpec, IMMSpec, FadingSpec,
    VBRSpec, AkhlaghiSpec, VBAKFSpec, SWVBSpec, CMScaleSpec, SageHusaSpec, IAESpec, ALSSpec,
    KalmanNetSpec, AugmentedSpec, VBIMMSpec,
)  # fmt: skip
RECORDED_SOURCE = "anfekf_bench.sources.recorded"  # its TunedEKFSpec: the plain EKF too


def supported_type(spec: FilterSpec) -> bool:
    """Whether the fast engine implements this spec's filter (on some motion model)."""
    if type(spec) in SUPPORTED_SPECS:
        return True
    # A recorded scenario's ekf-tuned, looked up without importing its module (pandas and
    # pyarrow: a worker that never loaded a recording must not pay for them): a spec of that
    # class exists only once the module is loaded.
    recorded = sys.modules.get(RECORDED_SOURCE)
    return recorded is not None and type(spec) is recorded.TunedEKFSpec


def register() -> None:
    """Register the fast engine's kinds with the registry (for `anfekf kinds`); importing
    `engines.fast` registers its own `supports` in its place (kept, if it is loaded)."""
    if "anfekf_bench.engines.fast" not in sys.modules:
        register_engine("fast", supported_type)
