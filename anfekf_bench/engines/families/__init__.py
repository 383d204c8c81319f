"""The families of the fast engine's loop (`engines/loop.py`), one module each: its `Params`,
`params(spec, ctx)` and its hooks (loop.HOOKS).

A spec class names its module here by `fast_family` (filters.spec; declared on exactly that
class), the one place that says a kind runs on the loop (docs/DESIGN.md, "One loop, one module
per family"): no list of modules to extend.
"""

from __future__ import annotations

import importlib

from ...filters.spec import fast_family_of
from .. import kernels as _kernels


def module(name: str, pure: bool = False):
    """The family module `name` (pure: its plain-Python copy)."""
    mod = importlib.import_module(f"{__name__}.{name}")
    return _kernels.pure_copy(mod.__name__, mod.__file__) if pure else mod


def for_spec(spec, pure: bool = False):
    """The family module that `spec`'s class names (`fast_family`), or None."""
    name = fast_family_of(spec)
    return None if name is None else module(name, pure)
