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
    # 12 s: acquisition off this hatch can take several scans (seed 0: 5 s of search, PAH's first
    # four answers 7-14 deg off and rejected for points seen through the model), and the
    # comparison needs a few tens of tracking frames.
    sc = Scenario("hold", cfg, target, 12.0, lambda t: T, None)
    result = replay(sc, seed=0)
    row, bins = summarise(result)
    assert row["acquisitions"] == 1
    (b,) = bins
    assert b["range_m"] == "0-10"  # the bins use the range to the docking port
    assert b["frames"] >= 10
    rec = result["rec"]
    ok = rec["valid"]
    # Recomputed from the published poses: the port under the estimate vs under the truth.
    assert np.all(np.isfinite(rec["port_err"][ok])) and np.all(np.isnan(rec["port_err"][~ok]))
    # Measured over seeds 0-2: port 2.6-3.3 mm RMS (max 9 mm), centre of mass 8.7-9.9 mm RMS,
    # attitude 0.04-0.05 deg RMS over 28-52 frames. An 8 s hold before ray crossings were
    # bounded by the noise: port 3.0-10.8 mm, centre of mass 9-21 mm, attitude up to 0.65 deg.
    # With the petals as cubes and closest-face matching: port 16-20 mm, centre of mass 34-52 mm.
    assert b["port_rms_mm"] < 0.7 * b["pos_rms_mm"]
    assert b["port_rms_mm"] < 15.0 and b["port_max_mm"] < 50.0


def test_recoveries_count_same_instant_reacquisitions() -> None:
    """A planned restart reacquired from the track's own prediction leaves and re-enters tracking
    at one instant; it is recovered at once, not when the next drop recovers (a bug that counted
    the last restart of the V-bar replay as unrecovered and reported 238 s median reacquisition)."""
    import types

    from agents.benchmarks.pipeline import _recoveries
    from perception.pipeline.modes import ModeEvent
    from perception.pipeline.state import Mode

    T, S, B = Mode.TRACKING, Mode.SEARCH, Mode.BEARING
    ev = [ModeEvent(0.0, B, S, ""), ModeEvent(1.0, S, T, ""),
          ModeEvent(300.0, T, S, "planned restart"), ModeEvent(300.0, S, T, "acquired"),
          ModeEvent(450.0, T, S, "loss"), ModeEvent(456.2, S, T, "acquired"),
          ModeEvent(600.0, T, S, "planned restart"), ModeEvent(600.0, S, T, "acquired"),
          ModeEvent(700.0, T, S, "loss")]
    result = {"tri": types.SimpleNamespace(logic=types.SimpleNamespace(events=ev))}
    drops, recovered, times = _recoveries(result)
    assert (drops, recovered) == (4, 3)
    np.testing.assert_allclose(times, [0.0, 6.2, 0.0])
