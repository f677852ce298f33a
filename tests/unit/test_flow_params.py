"""Method parameters are type-checked when the method is built, not at the first frame."""

from __future__ import annotations

import pytest

from flow.deepmatching import MatchParams
from flow.variational import VariationalParams


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
