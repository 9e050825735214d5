"""The pipeline benchmark's error bins: centre-of-mass and docking-port errors against truth."""

from __future__ import annotations

import numpy as np

from agents.benchmarks.pipeline import Scenario, replay, summarise
from perception.config import load_config
from perception.pipeline import approach_pose
from perception.targets import load_target


def test_port_errors_are_reported_and_smaller_than_centre_of_mass_errors() -> None:
    """Holding 4 m off the ISS-like port: the sensor sees the port area, 11.7 m from the centre
    of mass, so an attitude error moves the centre of mass by the lever arm and the port not."""
    cfg = load_config("final_approach")
    target = load_target("iss_port")
    T = approach_pose(cfg, target, 4.0)
    sc = Scenario("hold", cfg, target, 8.0, lambda t: T, None)
    result = replay(sc, seed=0)
    row, bins = summarise(result)
    assert row["acquisitions"] == 1
    (b,) = bins
    assert b["range_m"] == "10-20"  # the bins use the range to the centre of mass
    assert b["frames"] >= 10
    rec = result["rec"]
    ok = rec["valid"]
    # Recomputed from the published poses: the port under the estimate vs under the truth.
    assert np.all(np.isfinite(rec["port_err"][ok])) and np.all(np.isnan(rec["port_err"][~ok]))
    # Measured over seeds 0-2: port 16-20 mm RMS, centre of mass 34-52 mm RMS (attitude
    # 0.3-0.7 deg RMS over 32 frames, so the ratio moves with the seed).
    assert b["port_rms_mm"] < 0.7 * b["pos_rms_mm"]
    assert b["port_rms_mm"] < 25.0 and b["port_max_mm"] < 50.0
