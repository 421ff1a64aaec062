"""The base of every YAML-facing settings model, and the number types they share.

Strict: an unknown key is an error, numbers stay numbers (no "5" for 5) and are finite. Each settings
model lives beside the code that reads it (Klipper's rule: an object reads its own section);
``motorctl.config`` composes them into the file's schema and adds the cross-field checks.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator

#: the magnitudes a number of a gantry's config can have, in SI units, where its key states no
#: range of its own: 0, or between these (a subnormal 5e-324 or a 1e300 is no physical value, and
#: would overflow the arithmetic that plans moves and budgets)
MAGNITUDE_MIN = 1e-15
MAGNITUDE_MAX = 1e12


def quantity(lo: float, hi: float, unit: str, *, open_lo: bool = False):
    """A float key with the physical range a gantry can have, stated with its unit: ``lo`` ≤ x
    ≤ ``hi`` [unit] (``open_lo``: ``lo`` < x). A value outside is refused with the value, the
    range and the unit (the config error names the key). The range is also in the model's JSON
    schema (``unit``, ``range``)."""
    low = "(" if open_lo else "["

    def check(x: float) -> float:
        if not ((lo < x) if open_lo else (lo <= x)) or not x <= hi:
            raise ValueError(f"{x:g} {unit} is outside the physical range {low}{lo:g}, {hi:g}] {unit}")
        return x

    return Annotated[float, AfterValidator(check), Field(json_schema_extra={"unit": unit, "range": [lo, hi]})]


#: a position along a gantry's stroke [m]
Position_m = quantity(-100.0, 100.0, "m")
#: a time in a program or a run [s] (up to a day)
Time_s = quantity(0.0, 86400.0, "s")
#: a float > 0
Pos = Annotated[float, Field(gt=0)]
#: a float >= 0
NonNeg = Annotated[float, Field(ge=0)]
#: six floats (θ1..θ6)
Vec6 = Annotated[list[float], Field(min_length=6, max_length=6)]


def _magnitude(x: Any) -> None:
    if isinstance(x, float) and x != 0.0 and not MAGNITUDE_MIN <= abs(x) <= MAGNITUDE_MAX:
        raise ValueError(f"{x:g} is no physical value of a gantry: a number here is 0 or between "
                         f"{MAGNITUDE_MIN:g} and {MAGNITUDE_MAX:g} in magnitude (SI units)")
    if isinstance(x, (list, tuple)):
        for v in x:
            _magnitude(v)


class StrictModel(BaseModel):
    """Base of every YAML-facing options model: unknown keys are errors, numbers stay numbers,
    and every float is finite (``.inf`` and ``.nan`` are refused: an infinite following-error
    limit would switch the protection off by accident) and of a physical magnitude (0, or
    :data:`MAGNITUDE_MIN` to :data:`MAGNITUDE_MAX` in SI units, where the key's own
    :func:`quantity` range says nothing narrower)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _physical_magnitude(cls, v):
        _magnitude(v)
        return v
