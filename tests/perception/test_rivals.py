"""The rival monitor: a registration the filter's gate rejected stands as a rival pose, its port
offset on the protection level, until registrations that observe the disputed direction rule it
out; and the filter methods it stands on."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from perception.config import load_config
from perception.geometry import make_T
from perception.pipeline.filter import PoseFilter
from perception.pipeline.integrity import integrity_factor, port_covariance, protection_level
from perception.pipeline.publish import FrameOutput, Publisher
from perception.pipeline.rivals import RivalMonitor
from perception.pipeline.state import Mode

R_PORT = np.array([0.0, 0.0, -1.2])  # the port 1.2 m in front of the target origin
T_TRUE = make_T(np.eye(3), [0.0, 0.0, 5.6])  # the port 4.4 m down the boresight
SP, SA = 0.0015, np.radians(0.05)  # a registration's claimed sigmas [m, rad]
UNOBSERVED = 1.0e6
PL_FACTOR = integrity_factor(1e-5)
ALERT_M = 0.05


def _filter(T0: np.ndarray) -> PoseFilter:
    """A filter on a still pose ``T0``, its rates settled by 40 frames of it at 5 Hz (t = 8 s)."""
    f = PoseFilter(accel_psd=2e-5, angacc_psd=2e-5, ref_point=R_PORT)
    f.initialize(0.0, T0, _cov())
    for k in range(1, 41):
        assert f.update(0.2 * k, T0, _cov()).accepted
    return f


def _cov(unobserved: tuple[int, ...] = ()) -> np.ndarray:
    """A registration's covariance about the target origin; ``unobserved`` indices (0-2 tx-tz,
    3-5 rx-rz) left to ICP's 1e6, as a flat face seen head-on leaves tx, ty, rz."""
    d = np.array([SP**2] * 3 + [SA**2] * 3)
    d[list(unobserved)] = UNOBSERVED
    return np.diag(d)


def _monitor(votes: int | None = 3) -> RivalMonitor:
    return RivalMonitor(SimpleNamespace(pc=SimpleNamespace(integrity=SimpleNamespace(rival_votes=votes))))  # type: ignore[arg-type]


def _port(T: np.ndarray) -> np.ndarray:
    return T[:3, :3] @ R_PORT + T[:3, 3]


def test_mahalanobis2_is_the_gates_statistic_and_leaves_the_filter_alone() -> None:
    f = _filter(T_TRUE)
    T = make_T(np.eye(3), T_TRUE[:3, 3] + [0.003, -0.002, 0.001])
    p, P = f.p.copy(), f.P.copy()
    d2 = f.mahalanobis2(8.2, T, _cov())
    assert np.array_equal(f.p, p) and np.array_equal(f.P, P) and f.t == 8.0
    g = f.copy()
    assert g.update(8.2, T, _cov()).mahalanobis2 == d2


def test_moved_to_takes_the_registration_along_what_it_observes_and_nothing_else() -> None:
    f = _filter(T_TRUE)
    off = np.array([0.04, 0.10, 0.003])
    T = make_T(np.eye(3), T_TRUE[:3, 3] + off)
    # All six observed: the moved pose is the registration's.
    full = f.moved_to(T, _cov())
    np.testing.assert_allclose(full.pose_at(f.t), T, atol=1e-12)
    # A flat face's registration (tx, ty, rz unobserved): only its depth is taken.
    flat = f.moved_to(T, _cov((0, 1, 5)))
    np.testing.assert_allclose(_port(flat.pose_at(f.t)) - _port(f.pose_at(f.t)), [0.0, 0.0, 0.003], atol=1e-12)
    np.testing.assert_allclose(flat.R, f.R, atol=1e-12)
    assert np.array_equal(flat.P, f.P) and np.array_equal(flat.W, f.W) and flat.t == f.t


def test_a_rejected_registration_stands_until_registrations_that_see_the_dispute_rule_it_out() -> None:
    f = _filter(T_TRUE)
    mon = _monitor(3)
    rival_T = make_T(np.eye(3), T_TRUE[:3, 3] + [0.0, 0.10, 0.0])
    assert f.mahalanobis2(8.2, rival_T, _cov()) > f.gate
    assert not f.update(8.2, rival_T, _cov()).accepted
    mon.rejected(f, rival_T, _cov())
    assert mon.offset_m(f) == pytest.approx(0.10, abs=1e-9)
    # Registrations that leave the disputed axis (ty) unobserved, however many, rule nothing out.
    t = 8.2
    for _ in range(10):
        t += 0.2
        T = make_T(np.eye(3), T_TRUE[:3, 3] + [0.0, 0.03, 0.0])  # ty is wherever ICP left it
        assert f.update(t, T, _cov((0, 1, 5))).accepted
        mon.accepted(t, T, _cov((0, 1, 5)))
    assert mon.rival is not None and mon.votes == 0
    assert mon.offset_m(f) == pytest.approx(0.10, abs=1e-3)
    # Three that observe it, beyond the gate from the rival: it falls.
    for k in range(3):
        assert mon.rival is not None
        t += 0.2
        assert f.update(t, T_TRUE, _cov()).accepted
        mon.accepted(t, T_TRUE, _cov())
        assert mon.votes == (k + 1) % 3
    assert mon.rival is None and mon.offset_m(f) == 0.0
    # Off (rival_votes None): nothing ever stands.
    off = _monitor(None)
    off.rejected(f, rival_T, _cov())
    assert off.rival is None and off.offset_m(f) == 0.0


def test_a_rival_that_comes_back_needs_twice_the_votes_and_a_restart_judges_afresh() -> None:
    f = _filter(T_TRUE)
    mon = _monitor(3)
    rival_T = make_T(np.eye(3), T_TRUE[:3, 3] + [0.0, 0.10, 0.0])
    mon.rejected(f, rival_T, _cov())
    assert mon.needed == 3
    mon.rejected(f, rival_T, _cov())
    assert mon.needed == 6
    mon.rejected(f, rival_T, _cov())
    assert mon.needed == 12
    old = f.copy()
    mon.replaced(old)
    assert mon.needed == 3 and mon.returns == 0 and mon.offset_m(old) == 0.0
    for _ in range(20):
        mon.rejected(f, rival_T, _cov())
    assert mon.needed == 3 << 10  # capped


def _published(out: FrameOutput, pc) -> float:  # type: ignore[no-untyped-def]
    pub = Publisher(pc, R_PORT, max_pose_age=1.0)
    pub.append(out)
    return float(pub.publish(out.t_meas, Mode.TRACKING, None).protection_level)


def test_the_publisher_adds_the_rivals_port_offset_to_the_protection_level() -> None:
    cfg = load_config("final_approach")
    f = _filter(T_TRUE)
    kw = dict(available_t=0.0, mode=Mode.TRACKING, kind="pose", t_meas=0.0, n_points=500,
              fitness=1.0, filt=f, n_updates=5, lever_m=0.5)
    base = _published(FrameOutput(**kw), cfg.pipeline)  # type: ignore[arg-type]
    more = _published(FrameOutput(**kw, rival_m=0.07), cfg.pipeline)  # type: ignore[arg-type]
    assert more - base == pytest.approx(0.07, abs=1e-12)


def _false_basin_run(votes: int | None, seed: int) -> tuple[int, int]:
    """A track PAH started in a false basin 10 cm off in a flat face's plane, under ICP's
    millimetre covariance; the frames that follow as on hubble (reset seed 923): most
    registrations leave the in-plane axes unobserved, and those that observe them land in either
    basin, one in two. Returns ``(hazardous frames, valid frames)`` from the first registration
    of the right basin on (before it, nothing says the track is not the truth): valid (n >= 3
    updates, PL within the alert limit) with the port error beyond the protection level. The
    gate's rejections restart nothing here (no two in a row)."""
    rng = np.random.default_rng(seed)
    false_T = make_T(np.eye(3), T_TRUE[:3, 3] + [0.0, 0.10, 0.0])
    f = _filter(false_T)
    mon = _monitor(votes)
    kinds = "DDTDDFTDFDDDDFFDDDTDDFDTDDFFDDT"  # D: flat (tx ty rz unobserved); F/T: false/true basin
    hazards = valid = 0
    n_updates = 1
    seen = False
    t = f.t
    for kind in kinds:
        t += 0.2
        noise = np.concatenate([rng.normal(0.0, SP, 3), rng.normal(0.0, SA, 3)])
        T = make_T(np.eye(3), T_TRUE[:3, 3] + noise[:3] + ([0.0, 0.10, 0.0] if kind == "F" else 0.0))
        cov = _cov((0, 1, 5)) if kind == "D" else _cov()
        if kind == "D":
            T[:3, 3] += [rng.normal(0.0, 0.03), rng.normal(0.0, 0.03), 0.0]  # where ICP left it
        if f.update(t, T, cov).accepted:
            n_updates += 1
            mon.accepted(t, T, cov)
        else:
            mon.rejected(f, T, cov)
        _, _, R, _, P = f.target_state()
        pl = protection_level(port_covariance(P, R, R_PORT), PL_FACTOR) + mon.offset_m(f)
        err = float(np.linalg.norm(_port(f.pose_at(t)) - _port(T_TRUE)))
        seen = seen or kind == "T"
        if seen and n_updates >= 3 and pl <= ALERT_M:
            valid += 1
            hazards += err > pl
    return hazards, valid


def test_a_track_in_a_false_basin_is_not_published_valid_while_the_right_basin_keeps_coming() -> None:
    """Without the monitor the false track is published valid 10 cm off under a bound of a few
    centimetres in most frames once the right basin has shown; with it (3 votes, doubled on
    each return), never."""
    for seed in range(20):
        hazards, valid = _false_basin_run(None, seed)
        assert hazards >= 10 and valid >= hazards
        hazards, _ = _false_basin_run(3, seed)
        assert hazards == 0


def test_a_standing_rival_moves_with_the_host_as_the_track_does() -> None:
    """A rival is the same target seen from the same host: the host's thrust, which the track's
    filter takes from the accelerometer, carries the rival too, and the port offset between the
    two stays what it was when the rival stood. (Left on the motion it had then, a rival that
    stood before a burn went 1 m off the track over the burn: all of it on the protection level.)"""
    from perception.pipeline import TriDAR, approach_pose
    from perception.pipeline.filter import EgoMotion
    from perception.shapes import generate_target

    cfg = load_config("final_approach")
    assert cfg.pipeline.ego_motion and cfg.pipeline.integrity.rival_votes is not None
    target = generate_target("assembly", 7)
    tri = TriDAR(cfg, target)
    T0 = approach_pose(cfg, target, 5.0)
    still = EgoMotion(np.zeros(3), np.zeros(3))
    tri.take_ego(0.0, still)
    tri.filter.initialize(0.0, T0, _cov())
    for k in range(1, 41):
        tri.take_ego(0.2 * k, still)
        assert tri.filter.update(0.2 * k, T0, _cov()).accepted
    t = 8.0
    off = make_T(np.eye(3), [0.0, 0.10, 0.0])
    tri.rivals.rejected(tri.filter, off @ T0, _cov())
    assert tri.rivals.offset_m(tri.filter) == pytest.approx(0.10, abs=1e-9)
    # a 10 s burn of 2 cm/s^2 along the boresight, then 10 s of coasting, the sensor turning slowly
    for k in range(1, 101):
        t = 8.0 + 0.2 * k
        accel = np.array([0.0, 0.0, 0.02]) if k <= 50 else np.zeros(3)
        tri.take_ego(t, EgoMotion(np.array([0.0, 0.002, 0.0]), accel))
        assert tri.rivals.offset_m(tri.filter) == pytest.approx(0.10, abs=2e-4)
    assert tri.rivals.rival is not None and tri.rivals.rival.t == tri.filter.t == pytest.approx(t)
    # the host's motion moved both: the track is metres from where it stood
    assert np.linalg.norm(tri.filter.pose_at(t)[:3, 3] - T0[:3, 3]) > 1.0
