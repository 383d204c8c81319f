"""The kinds on the problems beyond the robot (SPEC 17), read from the filter registry.

The registry lists every kind once (`filters.registry.SPECS`). A kind that runs on a problem
besides the robot names its form here on its spec class (`FilterSpec.problem_form`,
"<module>:<class>" in this package): the spec class of its parameters on a problem (full Q and
R where the robot has sigmas) and its implementation. This module resolves those names, as the
fast engine resolves `fast_family`, so the registry imports no problem and there is no second
list of kinds: the problem scenario's `filters:` union, its error messages and the generated
docs are derived from `FORMS`.
"""

from __future__ import annotations

import importlib
from typing import Annotated, Union

from pydantic import Field

from ..filters.registry import kind_of, problem_forms
from .filters import ProblemFilterSpec


class FormError(TypeError):
    """A kind's `problem_form` does not name its spec class on the problems (a bug)."""


def resolve(kind: str, form: str | None) -> type[ProblemFilterSpec]:
    """The spec class `form` ("<module>:<class>") names for `kind`, or FormError."""
    if form is None:
        raise FormError(f"kind {kind!r} runs on a problem beyond the robot but its spec names"
                        " no problem_form")  # fmt: skip
    module, _, name = form.partition(":")
    cls = getattr(importlib.import_module(f"{__package__}.{module}"), name, None)
    if not (isinstance(cls, type) and issubclass(cls, ProblemFilterSpec)):
        raise FormError(f"kind {kind!r}: problem_form {form!r} is not a ProblemFilterSpec")
    if kind_of(cls) != kind:
        raise FormError(f"kind {kind!r}: problem_form {form!r} declares kind {kind_of(cls)!r}")
    return cls


# Every kind's form on the problems, in registry order.
FORMS: tuple[type[ProblemFilterSpec], ...] = tuple(resolve(k, f) for k, f in problem_forms())
PROBLEM_KINDS: tuple[str, ...] = tuple(kind_of(cls) for cls in FORMS)
AnyProblemFilter = Annotated[Union[FORMS], Field(discriminator="kind")]  # noqa: UP007
