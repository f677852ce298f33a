"""Property: whatever a user types into the scale, ROI, mask-shape and parameter options,
`refflow track` either measures (exit 0, finite numbers on valid frames) or refuses with
one line (exit 2); never a traceback, never a half-written output."""

from __future__ import annotations

import csv
import math
from datetime import timedelta

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flow.cli import main

W, H = 96, 64

numbers = st.one_of(st.integers(-200, 300).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                    st.sampled_from(["nan", "inf", "-inf", "", "abc", "1e400", " 3", "0x10"]))
quads = st.lists(numbers, min_size=0, max_size=6).map(",".join)
options = st.one_of(
    st.tuples(st.just("--mm-per-px"), numbers),
    st.tuples(st.just("--known-length"), numbers, st.just("--between"), quads),
    st.tuples(st.just("--rect"), quads),
    st.tuples(st.just("--roi"), quads),
    st.tuples(st.just("--param"), st.sampled_from(["alpha", "n_outer", "reciprocal", "ngh_rad", "bogus"]).flatmap(
        lambda key: numbers.map(lambda value: f"{key}={value}"))),
    st.tuples(st.just("--fps"), numbers),
)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_frames")
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)), (0, 0), 2.0)
    for i in range(3):
        shifted = np.roll(base, i, axis=1)
        cv2.imwrite(str(folder / f"f{i}.png"), np.clip(shifted, 0, 255).astype(np.uint8))
    return folder


@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(option=options)
def test_any_option_value_measures_or_refuses_in_one_line(frames, tmp_path, capsys, option) -> None:
    out = tmp_path / "fuzz.csv"
    for stale in tmp_path.iterdir():
        stale.unlink()
    argv = ["track", str(frames), "--method", "deepflow" if option[0] == "--param" else "dis",
            "--no-progress", "--out", str(out)]
    if option[0] != "--fps":
        argv += ["--fps", "30"]
    if option[0] != "--rect":
        argv += ["--rect", "20,10,50,40"]
    try:
        rc = main([*argv, *option])
    except SystemExit as stop:  # argparse's own refusal (e.g. "-1e+16" read as an option)
        rc = stop.code
    err = capsys.readouterr().err.strip()
    assert rc in (0, 2), (option, err)
    assert "Traceback" not in err
    if rc == 2:
        errors = [line for line in err.splitlines() if ": error: " in line]
        assert len(errors) == 1, err
        assert not out.exists() and not out.with_suffix(".json").exists()
        return
    with out.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        if row["valid"] == "1":
            assert math.isfinite(float(row["dx_px"])) and math.isfinite(float(row["dy_px"])), (option, row)
            if row["dx_mm"] != "nan":
                assert math.isfinite(float(row["dx_mm"])), (option, row)


def _outside_text(param) -> st.SearchStrategy:
    """A value of ``param`` outside its declared range, as typed after ``--param KEY=``."""
    options = [st.sampled_from(["nan", "inf", "-inf", "1e400", "abc", ""])]
    if param.low is not None:
        options.append(st.floats(max_value=param.low, exclude_max=not param.low_open, allow_nan=False,
                                 allow_infinity=False).map(repr))
    if param.high is not None:
        options.append(st.floats(min_value=param.high, exclude_min=not param.high_open, allow_nan=False,
                                 allow_infinity=False).map(repr))
        options.append(st.integers(min_value=int(param.high) + 1).map(str))
    return st.one_of(*options)


@settings(max_examples=60, deadline=timedelta(seconds=3), derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_parameter_outside_its_range_is_refused_before_any_frame(frames, tmp_path, capsys, data) -> None:
    """Issue 32, case 6: `--param winsize=100000000` ran for 17 minutes. Whatever method and
    parameter, a value outside the declared range (`refflow methods --params NAME`) is one
    line at once, naming the parameter and pointing at the list; each example is bounded in
    time (the deadline), and no file is written."""
    from flow.methods import registry

    numeric = [(name, p) for name in registry.available() for p in registry.parameters(name)
               if p.kind in ("int", "float")]
    name, param = data.draw(st.sampled_from(numeric), label="parameter")
    value = data.draw(_outside_text(param), label="value")
    out = tmp_path / "p.csv"
    rc = main(["track", str(frames), "--fps", "30", "--rect", "20,10,50,40", "--method", name, "--no-progress",
               "--out", str(out), f"--param={param.name}={value}"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, (name, param.name, value, err)
    assert f"parameter {param.name}" in err and f"(see `refflow methods --params {name}`)" in err, err
    assert not out.exists() and not out.with_suffix(".json").exists()
