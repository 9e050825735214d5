"""The registrations' correlated error calibrated on the target's own model (perception.pipeline.calibration)."""

from __future__ import annotations

import numpy as np
import pytest

from perception.config import load_config
from perception.pipeline import TriDAR
from perception.pipeline.calibration import calibrate_accuracy, calibration_ranges
from perception.shapes import generate_target


def _calibrate(cfg, target, ranges, poses: int = 6, seed: int = 3):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    tri = TriDAR(cfg, target)
    tri.reset(rng)
    return tri, calibrate_accuracy(tri, ranges, poses, 3, rng)


def test_calibration_finds_the_time_of_flights_range_bias_along_the_line_of_sight() -> None:
    """A 3 cm range bias on the time of flight is a correlated error along the line of sight at
    every range it ranges (beyond the transition), the same at every aspect: the calibration
    reports it there (with the shape's own offset of a few millimetres), not across the line of
    sight, and not where triangulation ranges."""
    target = generate_target("assembly", 11)
    ranges = calibration_ranges(1.5, 42.5, 6)
    tri0, plain = _calibrate(load_config("final_approach", sensor__tof__bias_m=0.0), target, ranges)
    _, biased = _calibrate(load_config("final_approach", sensor__tof__bias_m=0.03), target, ranges)
    tof = tri0.sensor.transition_range_m
    seen = np.isfinite(biased.along_m)
    far = seen & (biased.range_m > 1.2 * tof)
    near = seen & (biased.range_m < 0.8 * tof)
    assert far.sum() >= 2 and near.sum() >= 1
    np.testing.assert_allclose(biased.along_m[far], 0.03, atol=0.008)
    assert np.all(plain.along_m[np.isfinite(plain.along_m) & (plain.range_m > 1.2 * tof)] < 0.012)
    # across it, millimetres within 30 m (the beam's footprint grows beyond)
    assert np.nanmax(biased.across_m[biased.range_m < 30.0]) < 0.008
    # triangulation does not see the time of flight's bias
    assert np.all(biased.along_m[near] < 0.012)
    # a figure is a 1-sigma over the aspects that observed it (NaN where none did)
    assert biased.samples.shape == (len(biased.range_m), 3) and biased.samples.max() <= 6
    assert np.array_equal(np.isfinite(biased.along_m), biased.samples[:, 0] > 0)
    # interpolated in range between the ranges that observed a figure
    a, b, _ = biased.at(0.5 * (biased.range_m[-2] + biased.range_m[-1]))
    assert min(biased.along_m[-2:]) <= b <= max(biased.along_m[-2:])
    assert biased.at(1e4) == biased.at(biased.range_m[-1])


def test_calibration_is_a_function_of_its_generator() -> None:
    """The same generator gives the same table bitwise, another generator another one."""
    target = generate_target("assembly", 7)
    cfg = load_config("final_approach")
    ranges = calibration_ranges(2.0, 20.0, 3)
    _, a = _calibrate(cfg, target, ranges, 4, 5)
    _, b = _calibrate(cfg, target, ranges, 4, 5)
    _, c = _calibrate(cfg, target, ranges, 4, 6)
    for f in ("range_m", "across_m", "along_m", "attitude_rad", "samples"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
    assert not np.array_equal(a.along_m, c.along_m, equal_nan=True)


def test_bad_calibration_settings_are_refused_with_the_value() -> None:
    with pytest.raises(ValueError, match=r"calibration ranges 5.0..2.0 m"):
        calibration_ranges(5.0, 2.0, 4)
    target = generate_target("assembly", 7)
    tri = TriDAR(load_config("final_approach"), target)
    with pytest.raises(ValueError, match="poses=3, repeats=1"):
        calibrate_accuracy(tri, calibration_ranges(2.0, 4.0, 2), 3, 1, np.random.default_rng(0))


def test_each_scan_of_an_aspect_is_the_tracks_next_frame() -> None:
    """The repeats of one aspect are scanned at successive pattern phases, as a track's frames
    are: with one phase for all of them, where that phase's samples fall on the shape was counted
    as a correlated error (on ten shapes the published position NEES was 0.7-1.8 for 1.0-2.8)."""
    target = generate_target("assembly", 7)
    tri = TriDAR(load_config("final_approach"), target)
    tri.reset(np.random.default_rng(0))
    seen: list[int] = []
    make = tri.sensor.make_scan_pattern

    def spy(frame_index, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(int(frame_index))
        return make(frame_index, *args, **kwargs)

    tri.sensor.make_scan_pattern = spy  # type: ignore[method-assign]
    calibrate_accuracy(tri, calibration_ranges(2.0, 20.0, 2), 2, 3, np.random.default_rng(1))
    frames = list(dict.fromkeys(seen))  # the scan planner predicts a frame's candidates at its index
    assert len(frames) >= 2 * 4  # two aspects, 1 + 3 scans each
    assert np.all(np.diff(frames) == 1)  # every scan one phase step on from the previous one
    phases = {round((k * tri.sensor.config.scan.phase_step) % (2 * np.pi), 9) for k in frames[:4]}
    assert len(phases) == 4
