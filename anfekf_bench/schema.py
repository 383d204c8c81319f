"""The strict pydantic base every typed parameter block derives from (scenario and filters alike).

Unknown keys are errors, values are frozen, and YAML true/false is never read as a number.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


def _holds_bool(value: object) -> bool:
    """True for a YAML true/false, also inside lists (but not inside nested mappings)."""
    if isinstance(value, bool):
        return True
    return isinstance(value, (list, tuple)) and any(_holds_bool(v) for v in value)


class StrictModel(BaseModel):
    """Base of every parameter block: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_as_number(cls, data: object) -> object:
        # pydantic would read `runs: true` as 1 run: only boolean fields may be true/false.
        if isinstance(data, dict):
            for key, value in data.items():
                field = cls.model_fields.get(key) if isinstance(key, str) else None
                if field is None or _holds_bool_allowed(field.annotation):
                    continue
                if _holds_bool(value):
                    raise PydanticCustomError(
                        "bool_as_number", "expected a number or text, not true/false", {"key": key}
                    )
        return data


def _holds_bool_allowed(annotation: object) -> bool:
    """Fields typed bool (or a free-form dict of a user's own parameters) may hold true/false."""
    return (
        annotation is bool or getattr(annotation, "__origin__", None) is dict or annotation is dict
    )
