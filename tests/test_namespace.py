"""The public namespace (`tippejax/__init__.py`): `__all__` is what `dir()` lists and every name
in it resolves; the internals once exported still import, with a DeprecationWarning."""

import importlib.resources

import pytest

import tippejax as tj
from tippejax._invariants import normal_force_denominator
from tippejax._models.routhian import CHART_SIN_MIN

DESIGN_NAMES = (
    "TippeTop",
    "classify",
    "thresholds",
    "initial_state",
    "jellet",
    "energy",
    "normal_force",
    "simulate",
    "effective_potential",
    "steady_states",
    "fit",
    "outcome_map",
    "OUTCOMES",
    "inversion_time",
)


def test_all_lists_the_public_names():
    assert len(set(tj.__all__)) == len(tj.__all__)
    for name in tj.__all__:
        assert getattr(tj, name) is not None, name
    assert set(dir(tj)) == {*tj.__all__, "__version__"}
    assert set(DESIGN_NAMES) <= set(tj.__all__)
    namespace = {}
    exec("from tippejax import *", namespace)
    assert {n for n in namespace if not n.startswith("__")} == set(tj.__all__)


@pytest.mark.parametrize(
    "name, value",
    [("CHART_SIN_MIN", CHART_SIN_MIN), ("normal_force_denominator", normal_force_denominator)],
)
def test_deprecated_internals_still_import_with_a_warning(name, value):
    assert name not in tj.__all__ and name not in dir(tj)
    with pytest.warns(DeprecationWarning, match=name):
        assert getattr(tj, name) is value
    namespace = {}
    with pytest.warns(DeprecationWarning, match=name):
        exec(f"from tippejax import {name}", namespace)
    assert namespace[name] is value


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        tj.not_a_name


def test_ships_py_typed():
    assert importlib.resources.files("tippejax").joinpath("py.typed").is_file()
