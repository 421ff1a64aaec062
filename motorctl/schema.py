"""The base of every YAML-facing settings model, and the number types they share.

Strict: an unknown key is an error, numbers stay numbers (no "5" for 5) and are finite. Each settings
model lives beside the code that reads it (Klipper's rule: an object reads its own section);
``motorctl.config`` composes them into the file's schema and adds the cross-field checks.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

#: a float > 0
Pos = Annotated[float, Field(gt=0)]
#: a float >= 0
NonNeg = Annotated[float, Field(ge=0)]
#: six floats (θ1..θ6)
Vec6 = Annotated[list[float], Field(min_length=6, max_length=6)]


class StrictModel(BaseModel):
    """Base of every YAML-facing options model: unknown keys are errors, numbers stay numbers,
    and every float is finite (``.inf`` and ``.nan`` are refused: an infinite following-error
    limit would switch the protection off by accident)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)
