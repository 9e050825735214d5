"""StateVector: every number is checked finite, whichever field it is in."""

from __future__ import annotations

import numpy as np
import pytest

from perception.pipeline.state import Mode, StateVector, Validity

FIELDS = {
    "t": np.inf, "range": np.nan, "range_rate": -np.inf, "fitness": np.nan, "latency": np.inf,
    "position": [0.0, np.nan, 0.0], "velocity": [np.inf, 0.0, 0.0],
    "quaternion": [1.0, 0.0, 0.0, np.nan], "angular_velocity": [0.0, 0.0, -np.inf],
    "bearing": [np.nan, 0.0],
}


@pytest.mark.parametrize("name", [*FIELDS, "covariance"])
def test_a_non_finite_number_anywhere_is_rejected(name: str) -> None:
    kw = {"t": 1.0, "mode": Mode.TRACKING, "valid": Validity()}
    if name == "covariance":
        cov = np.eye(12)
        cov[7, 3] = np.nan
        kw["covariance"] = cov
    else:
        kw[name] = FIELDS[name]
    with pytest.raises(ValueError, match="non-finite"):
        StateVector(**kw)


def test_a_finite_state_is_accepted_and_reports_finite() -> None:
    sv = StateVector(t=1.0, mode=Mode.TRACKING, valid=Validity(), position=[1.0, 2.0, 3.0],
                     range=3.7, covariance=np.eye(12) * 1e-4)
    assert sv.is_finite()
    sv.position[1] = np.nan  # mutated after construction: is_finite sees it
    assert not sv.is_finite()
