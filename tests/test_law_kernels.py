"""One table from a law's code to the step the servo cycle runs for it, and no fall-through: an
unknown code is refused when the loop takes the law, and the compiled dispatch, were it ever
handed one, runs no other law's step (its output NaN, which the supervisor faults)."""

from __future__ import annotations

import math

import pytest

import motorctl.control.base as base
from motorctl.control.kernels import LAW_KERNELS, LAW_PID, check_law_code, law_reset, law_step


def test_every_law_code_has_one_entry():
    codes = {v for k, v in vars(base).items() if k.startswith("LAW_") and isinstance(v, int)}
    assert codes == set(LAW_KERNELS)


@pytest.mark.parametrize("code", sorted(LAW_KERNELS))
def test_known_codes_pass(code):
    assert check_law_code(code, "c2") == code


@pytest.mark.parametrize("code", [99, -1, 1.0, True, None, "1"])
def test_unknown_code_is_refused_naming_the_law(code):
    with pytest.raises(ValueError, match=r"controller 'pd': law_code .* has no step in the servo cycle; known: 0 "):
        check_law_code(code, "pd")


def test_the_dispatch_does_not_fall_through_to_a_law():
    """The Python body of the compiled dispatch (numba's py_func): an unknown code touches no
    argument and returns NaN; the PID's code still reaches the PID's step (it needs its rows)."""
    assert math.isnan(law_step.py_func(99, *([None] * 12)))
    assert law_reset.py_func(99, 0.0, None, None) is None
    with pytest.raises(TypeError):
        law_step.py_func(LAW_PID, *([None] * 12))
