"""Method parameters are type-checked when the method is built, not at the first frame."""

from __future__ import annotations

import pytest

from flow.methods.deepflow.deepmatching import MatchParams
from flow.methods.deepflow.variational import VariationalParams


@pytest.mark.parametrize("field, value, message", [
    ("alpha", "abc", "alpha must be a finite number"),
    ("alpha", float("inf"), "alpha must be a finite number"),
    ("n_outer", 2.5, "n_outer must be an integer"),
    ("n_sor", True, "n_sor must be an integer"),
])
def test_variational_parameters_are_checked(field, value, message) -> None:
    with pytest.raises(ValueError, match=message):
        VariationalParams(**{field: value})


def test_match_parameters_are_checked_and_none_is_kept_where_allowed() -> None:
    assert MatchParams(ngh_rad=None).ngh_rad is None
    assert MatchParams(ngh_rad=40).ngh_rad == 40  # an int where a float is declared is fine
    with pytest.raises(ValueError, match="reciprocal must be true or false"):
        MatchParams(reciprocal="yes")
    with pytest.raises(ValueError, match=r"downscale must be an integer, got None"):
        MatchParams(downscale=None)


# Every parameter of every registered method has a declared type, default, range and meaning
# (issue 32, case 6: `--param winsize=100000000` ran for 17 minutes at 7.6 GB; `pyr_scale=5`
# and `downscale=0` were tracebacks at the first frame).

import math  # noqa: E402
from datetime import timedelta  # noqa: E402

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from flow.methods import registry  # noqa: E402
from flow.methods.params import Param  # noqa: E402

METHODS = registry.available()
NUMERIC = [(name, param) for name in METHODS for param in registry.parameters(name)
           if param.kind in ("int", "float")]


@pytest.mark.parametrize("name", METHODS)
def test_every_parameter_of_every_method_is_declared(name) -> None:
    """The declared table is exactly what the method reports in its sidecar, with the
    defaults it uses; every default lies in its own range."""
    table = registry.parameters(name)
    assert table and all(param.meaning for param in table)
    method = registry.get_method(name)
    used = method.params()
    assert [param.name for param in table] == list(dict.fromkeys(p.name for p in table))  # no name twice
    assert {param.name for param in table} == set(used), name
    for param in table:
        param.check(param.default)
        if param.name != "preset":  # deepflow's preset is reported as given
            assert used[param.name] == param.default, (name, param.name)


def _outside(param: Param) -> st.SearchStrategy:
    """Numbers just outside, far outside, or not numbers of ``param``'s kind at all."""
    below, above = [], []
    if param.low is not None:
        low = param.low
        below = [st.just(low) if param.low_open else st.nothing(),
                 st.floats(max_value=low, exclude_max=True, allow_nan=False, allow_infinity=False)]
        if param.kind == "int":
            below = [st.integers(max_value=int(math.ceil(low)) - 1)]
    if param.high is not None:
        high = param.high
        above = [st.just(high) if param.high_open else st.nothing(),
                 st.floats(min_value=high, exclude_min=True, allow_nan=False, allow_infinity=False)]
        if param.kind == "int":
            above = [st.integers(min_value=int(high) + 1)]
    wrong = [st.just(math.nan), st.just(math.inf), st.just(-math.inf), st.just("abc"), st.just(True)]
    if param.kind == "int":
        wrong.append(st.floats(allow_nan=False, allow_infinity=False).filter(lambda v: not v.is_integer()))
        wrong.append(st.just(1e12))
    return st.one_of(*below, *above, *wrong)


# Each example is bounded in time: a refusal must come at construction, before any work.
@settings(max_examples=300, deadline=timedelta(seconds=1), derandomize=True)
@given(data=st.data())
def test_a_value_outside_its_range_is_refused_at_once(data) -> None:
    name, param = data.draw(st.sampled_from(NUMERIC), label="parameter")
    value = data.draw(_outside(param), label="value")
    with pytest.raises(ValueError) as refused:
        registry.get_method(name, **{param.name: value})
    message = str(refused.value)
    assert f"parameter {param.name}" in message and param.range_text() in message, message
    assert "\n" not in message


@settings(max_examples=200, deadline=timedelta(seconds=1), derandomize=True)
@given(data=st.data())
def test_a_value_inside_its_range_is_accepted(data) -> None:
    name, param = data.draw(st.sampled_from(NUMERIC), label="parameter")
    if param.kind == "int":
        value = data.draw(st.integers(int(param.low), int(param.high)))
    else:
        value = data.draw(st.floats(param.low, param.high, exclude_min=param.low_open,
                                    exclude_max=param.high_open))
    assert registry.get_method(name, **{param.name: value}).params()[param.name] == value


@pytest.mark.parametrize("name, item, expected", [
    ("farneback", "winsize=100000000", "parameter winsize=100000000 is outside its range 3..101"),
    ("farneback", "poly_n=1000001", "parameter poly_n=1000001 is outside its range 3..11"),
    ("farneback", "pyr_scale=5", "parameter pyr_scale=5 is outside its range 0.1..0.9"),
    ("dis", "refinement_iterations=1e12", "parameter refinement_iterations must be an integer, got 1000000000000.0"),
    ("deepflow", "n_outer=1000000000", "parameter n_outer=1000000000 is outside its range 1..20"),
    ("deepflow", "downscale=0", "parameter downscale=0 is outside its range 1..8"),
    ("farneback", "bogus=1", "unknown parameter(s) bogus; farneback takes pyr_scale, levels"),
])
def test_the_reported_parameters_are_refused_before_any_frame(tmp_path, capsys, name, item, expected) -> None:
    """The cases of the report: one line naming the parameter, its value and range and where
    the list is; no video is opened (the input does not even exist) and nothing is written."""
    from flow.cli import main

    out = tmp_path / "o.csv"
    assert main(["track", str(tmp_path / "no-such-video.mp4"), "--rect", "0,0,8,8", "--method", name,
                 "--param", item, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and f"(see `refflow methods --params {name}`)" in err, err
    assert len(err.splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_methods_lists_every_parameter_with_its_range(capsys) -> None:
    from flow.cli import main

    for name in METHODS:
        assert main(["methods", "--params", name]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines[0].startswith(f"{name}: ")
        for param in registry.parameters(name):
            row = next(line for line in lines if line.split()[:1] == [param.name])
            assert param.range_text() in row and param.meaning in row and param.type_text() in row
    assert main(["methods", "--params", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown method 'nope'" in err and len(err.splitlines()) == 1
