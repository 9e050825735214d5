"""Collision avoidance on a lost or degraded track: dead reckoning, hold and retreat.

Shared by the scripted controllers (:mod:`agents.glideslope`, :mod:`agents.lqr`,
:mod:`agents.sync`). DESIGN.md, "Integrity": a controller never flies on a pose that is not valid;
close in it holds or retreats. It reads only the observation.

**Dead reckoning.** While the pose is *healthy* (position and velocity valid, not degraded) the
monitor keeps the last trusted position and velocity of a reference point of the target (the port
for the final-approach controllers, the target's centre of mass for sync), relative to the chaser's
centre of mass, in the chaser's body frame at that fix, treated as inertial for the length of a
hold. Between fixes it propagates them open loop with what the chaser itself did: the
acceleration of the action it returned (normalised thrust x ``max_thrust / mass``, the mass from
``fuel_fraction``), and its own rotation from the gyro. The point's own acceleration is left out:
the target's centre of mass falls freely with the chaser up to CW terms (``2 n v``, ~1e-4 m/s^2 at
5 cm/s), and a port held in LVLH turns about it at ``n`` (centripetal ``n^2 r`` ~1e-5 m/s^2 at
10 m). In the body frame, which turns at the gyro's rate ``w``, the point ``x`` then moves as
``x'' = -a - 2 w x x' - w x (w x x)`` (``x'`` its body-frame rate, the observation's convention).

Each healthy pose resets the position; its velocity is blended with the dead-reckoned one
(``k_fix_velocity``, a complementary filter through the known accelerations): the estimate's
velocity noise (1-1.5 cm/s RMS across the axis under 10 m on the full pipeline) would otherwise
drift a minute-long hold by a metre. A *degraded* pose (protection level above the alert limit)
still measures the distance along the docking axis well (a flat face seen head-on leaves the
in-plane directions loose, not the depth): its axial position replaces the dead-reckoned one and
its axial rate is blended in; the lateral ones stay dead-reckoned.

**Rule.** Each step :meth:`CollisionAvoidance.update` says one of:

``nominal``
    healthy pose (and, after an avoidance, healthy for as long as it was lost, at most and after
    a retreat ``resume_s``): the controller flies its law.
``blind``
    no pose yet this episode (acquisition): nothing to dead-reckon from; the controller's own
    loss-of-pose rule applies (brake a closing range rate along the line of sight, else coast). A
    degraded pose before any healthy one starts the dead reckoning (for avoidance only).
``commit``
    the pose was lost (invalid, not degraded) while the last healthy state was inside
    ``commit_range_m`` of the port, within ``commit_lateral_m`` of the axis, closing inside the
    capture envelope's axial speed window and with a lateral speed under ``commit_lateral_speed``:
    braking there would turn a docking into a too-slow contact, so the chaser coasts into contact
    (in its own rotating frame: the centripetal and Coriolis terms of its rate are served, which is
    zero thrust for a chaser that does not turn). The decision is latched until contact or a
    healthy pose.
``avoid``
    otherwise (invalid or degraded, with a fix): brake the closing speed to zero and hold; when no
    healthy pose has come back within ``hold_s`` (a flicker of the flags is not worth a retreat),
    or at once when the chaser was inside ``commit_range_m`` (an abort), retreat along the approach
    axis to the hold point. Never close in. A retreat resumes on a healthy pose only once the port
    is at least ``commit_range_m`` ahead again: on Rendezvous-v0 a pose turned degraded 7 cm from
    contact, the abort braked to 0.027 m/s, the pose came back healthy 1 s later 2.6 cm out, and
    the resumed approach touched at 0.049 m/s, under the envelope's 0.05 (a collision).
    Retreating, the desired opening rate along the axis is
    ``clip(k_hold (s_hold - s), 0, v_retreat)`` (``s`` the distance along
    the axis: dock to port along the docking axis for glideslope/LQR; centre of mass to centre of
    mass for sync, whose axis is the line to the target's centre of mass), across it zero; a speed
    loop ``kv`` tracks it, plus the rotating-frame terms. ``s_hold`` is the controller's hold
    distance plus the protection level of a degraded pose. A degraded pose beyond ``s_hold``
    (still measured along the axis) closes to it at ``min(k_hold (s - s_hold), v_degraded_close)``
    (default 0: it holds where it is): the features that settle a degraded pose may only resolve
    closer in (a generated cylinder bus's roll, pinned by a thin boom that gave 0-3 returns a
    frame at 33 m, held degraded there for the whole episode), and ``s_hold`` keeps the
    protection level's width between the chaser and the port. A degraded pose inside the commit range
    aborts (it backs away too) unless the chaser is closer than the avoidance law can stop from
    (``closing / kv``) and the port is bounded inside the capture envelope's lateral tolerance
    (``lateral_max_m``): then it commits (latched), since braking there cannot stop the chaser and
    only turns a capture into a too-slow contact. The lateral offset is the dead-reckoned one, and
    two honest bounds can put it inside: the degraded pose's protection level, or the last healthy
    fix's protection level grown at ``commit_lateral_speed`` over the time since that fix plus the
    time to contact (the bound a lost pose's commit relies on). Either is enough. Measured: a
    generated assembly's track turned degraded 4.6 cm from contact (protection level 8.0 cm, alert
    limit 8 cm, envelope 10 cm; an abort touched at 0.029 m/s, a collision); on Rendezvous-v0 a
    false slide of the port patch 3-7 cm from contact raised the protection level from 4 cm to
    19 cm in one step, 7 of 100 runs aborted into too-slow contacts, and the last fix (0.5 s old,
    4 cm) bounded the port within 7 cm. Further out it still aborts: a 2.5 m plate's pose turned
    degraded 34 cm out with its bound growing 5 mm/s, and a commit there would have outlived the
    bound. A lost pose off axis or too fast aborts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from tridar_env.env import observation_slices

_S = observation_slices()
FloatArray = npt.NDArray[np.float64]

#: ``valid`` flags (observation order).
_POS, _VEL, _DEGRADED = 3, 4, 7

Mode = Literal["nominal", "blind", "commit", "avoid"]


@dataclass
class SafetyGains:
    """Tunables of :class:`CollisionAvoidance` (SI units)."""

    hold_range_m: float = 5.0  # [m] hold distance along the approach axis (see ``axis``)
    v_retreat: float = 0.05  # [m/s] opening speed of a retreat to the hold point
    k_hold: float = 0.05  # [1/s] opening speed = k_hold * (hold - distance), up to v_retreat
    kv: float = 0.4  # [1/s] speed loop
    commit_range_m: float = 0.4  # [m] a healthy pose lost closer than this may coast into contact
    commit_lateral_m: float = 0.05  # [m] ... when the dock is this close to the port axis
    commit_lateral_speed: float = 0.02  # [m/s] ... drifting across it no faster than this
    resume_s: float = 1.0  # [s] of healthy poses before an approach resumes (at most as long as
    # the pose was lost, unless the chaser retreated)
    k_fix_velocity: float = 0.1  # weight of a pose's velocity against the dead-reckoned one
    hold_s: float = 3.0  # [s] a loss shorter than this only stops the closing; then retreat
    v_degraded_close: float = 0.0  # [m/s] a degraded pose beyond the hold point closes to it
    # along the axis at most this fast (0: it holds where it is; module docstring)


def rotvec_matrix(rotvec: FloatArray) -> FloatArray:
    """Rotation matrix of a rotation vector [rad] (Rodrigues)."""
    th = float(np.linalg.norm(rotvec))
    if th < 1e-12:
        return np.eye(3)
    k = rotvec / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


class DeadReckoning:
    """A target point's position and rate relative to the chaser's centre of mass, propagated
    open loop between fixes (module docstring).

    Two models. Without ``model``: free fall in the inertial frame, the body's rotation from the
    gyro; internally the position ``X`` and inertial velocity ``V`` in the body frame of the last
    fix and ``R`` the body's attitude in that frame. With ``model = (A (6, 6), B (6, 3))``, the
    discrete relative dynamics of the chaser ``[r, v] = -[x, x']`` in a body frame that is constant
    in LVLH (the CW model of :func:`agents.lqr.docking_frame_model`): minutes of hold then do not
    drift by the Coriolis and tidal terms (2 n v, 3 n^2 x), which free fall would leave out.

    The CW terms act on the chaser's position from the target's centre of mass, so the model
    needs where the point sits from it: ``lever``, body frame (constant with the frame).

    Args:
        model: the discrete ``(A, B)`` over the controller step, or ``None``.
        lever: (3,) the point from the target's centre of mass, body frame [m] (with ``model``).
    """

    def __init__(
        self,
        model: tuple[FloatArray, FloatArray] | None = None,
        lever: npt.ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        self.model = model
        self._c = np.concatenate([np.asarray(lever, dtype=np.float64).reshape(3), np.zeros(3)])
        self.X = np.zeros(3)
        self.V = np.zeros(3)
        self.R = np.eye(3)

    def fix(self, x: FloatArray, x_dot: FloatArray, w: FloatArray) -> None:
        """Set from a body-frame position ``x`` [m], its body-frame rate ``x_dot`` [m/s] and the
        gyro ``w`` [rad/s]; the current body frame becomes the reference."""
        self.R = np.eye(3)
        self.reset_to(x, x_dot, w)

    def reset_to(self, x: FloatArray, x_dot: FloatArray, w: FloatArray) -> None:
        """Overwrite the state with body-frame values, keeping the reference frame."""
        x = np.asarray(x, dtype=np.float64)
        x_dot = np.asarray(x_dot, dtype=np.float64)
        if self.model is not None:
            self.X, self.V = x.copy(), x_dot.copy()
            return
        self.X = self.R @ x
        self.V = self.R @ (x_dot + np.cross(w, x))

    def predict(self, a_body: FloatArray, w: FloatArray, dt: float) -> None:
        """Advance ``dt`` [s] (the model's step when there is one) under the chaser's body
        acceleration ``a_body`` [m/s^2] and rate ``w`` [rad/s], both held over the step."""
        a_body = np.asarray(a_body, dtype=np.float64)
        if self.model is not None:
            A, B = self.model
            # chaser from the target's centre of mass = -x + lever
            s = A @ (self._c - np.concatenate([self.X, self.V])) + B @ a_body - self._c
            self.X, self.V = -s[:3], -s[3:]
            return
        # a body-fixed thrust turns with the body over the step: mean direction at the midpoint
        half = rotvec_matrix(np.asarray(w, dtype=np.float64) * (0.5 * dt))
        a = self.R @ half @ a_body
        self.X = self.X + self.V * dt - 0.5 * a * dt * dt
        self.V = self.V - a * dt
        self.R = self.R @ half @ half

    def state(self, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Body-frame position [m] and its body-frame rate [m/s] at gyro rate ``w``."""
        if self.model is not None:
            return self.X.copy(), self.V.copy()
        x = self.R.T @ self.X
        return x, self.R.T @ self.V - np.cross(w, x)


class CollisionAvoidance:
    """Integrity monitor and collision-avoidance law (see the module docstring).

    Args:
        dt: controller step [s].
        dock: (3,) dock origin in the chaser body frame [m] (the docking frame's origin; its axes
            are the body axes).
        envelope: ``(min, max)`` closing speed at contact [m/s] (the capture envelope).
        gains: tunables.
        axis: ``"dock"``: hold and retreat along the docking axis, distances dock-to-port;
            ``"radial"``: along the line to the reference point, distances centre to centre.
        model: discrete relative dynamics ``(A, B)`` in a body frame constant in LVLH (see
            :class:`DeadReckoning`); ``None``: free fall and the gyro.
        lever: (3,) the reference point from the target's centre of mass in that frame [m]
            (with ``model``).
        lateral_max_m: the capture envelope's lateral tolerance [m]: a pose that turns degraded
            inside the stopping distance still commits when the port is bounded inside it (module
            docstring; ``None``: a degraded pose there always aborts).

    Usage per step: ``mode = ca.update(obs, x, x_dot, port_offset)`` with the controller's
    reference point measured in this observation (ignored unless the pose is valid), then
    ``ca.accel(obs)`` when the mode is ``avoid`` or ``commit``, and always ``ca.applied(a)`` with
    the body acceleration the returned action commands.
    """

    def __init__(
        self,
        dt: float,
        dock: npt.ArrayLike,
        envelope: tuple[float, float],
        gains: SafetyGains | None = None,
        axis: Literal["dock", "radial"] = "dock",
        model: tuple[FloatArray, FloatArray] | None = None,
        lever: npt.ArrayLike = (0.0, 0.0, 0.0),
        lateral_max_m: float | None = None,
    ) -> None:
        self.dt = float(dt)
        self.lateral_max_m = None if lateral_max_m is None else float(lateral_max_m)
        self.d = np.asarray(dock, dtype=np.float64).reshape(3)
        self.envelope = (float(envelope[0]), float(envelope[1]))
        self.g = gains or SafetyGains()
        self.axis = axis
        self.model = model
        self.lever = np.asarray(lever, dtype=np.float64).reshape(3)
        self.reset()

    def reset(self) -> None:
        """Forget the episode: no fix, nominal."""
        self.dr = DeadReckoning(self.model, self.lever)
        self.has_fix = False
        self.mode: Mode = "nominal"
        self._avoided = False  # an avoidance since the last resume
        self._lost = 0  # consecutive steps without a healthy pose in this avoidance
        self._lost_s = 0.0  # longest such run since the last resume [s]
        self.retreating = False  # this avoidance backs away to the hold point (latched)
        self._healthy = 0  # consecutive healthy steps
        self._port_offset = np.zeros(3)  # port from the reference point, body frame [m]
        self._a_prev = np.zeros(3)
        self._w_prev = np.zeros(3)
        self._pl = 0.0  # protection level of the latest degraded pose [m]
        self._pl_fix = 0.0  # protection level of the last healthy fix [m]
        self._since_fix_s = 0.0  # time since the last healthy fix [s]
        self._degraded_commit = False  # committed on a degraded pose (latched, module docstring)
        self._degraded_now = False  # this step's pose is degraded (measured along the axis)

    # ------------------------------------------------------------------ state
    def port(self, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Dead-reckoned port position in the docking frame [m] and its rate [m/s]."""
        x, x_dot = self.dr.state(w)
        return x + self._port_offset - self.d, x_dot

    def update(
        self,
        obs: npt.NDArray[np.floating],
        x: FloatArray | None,
        x_dot: FloatArray | None,
        port_offset: FloatArray | None = None,
    ) -> Mode:
        """Propagate, take this observation's fix (healthy) or axial update (degraded), decide.

        Args:
            obs: the observation.
            x: the reference point from the chaser's centre of mass, body frame [m], as this
                observation measures it (``None`` when the position is not valid).
            x_dot: its body-frame rate [m/s] (``None`` when the velocity is not valid).
            port_offset: port minus reference point, body frame [m] (default zero: the reference
                point is the port).
        """
        valid = obs[_S["valid"]]
        w = obs[_S["chaser_rate_body"]].astype(np.float64)
        if self.has_fix:
            self.dr.predict(self._a_prev, self._w_prev, self.dt)
            self._since_fix_s += self.dt
        self._w_prev = w
        pose = x is not None and x_dot is not None and valid[_POS] > 0.5 and valid[_VEL] > 0.5
        degraded = valid[_DEGRADED] > 0.5 and x is not None and valid[_POS] > 0.5
        self._degraded_now = degraded
        if pose and not degraded:
            assert x is not None and x_dot is not None
            if self.has_fix:  # average the estimate's velocity noise through the model
                x_dot_pred = self.dr.state(w)[1]
                x_dot = x_dot_pred + self.g.k_fix_velocity * (x_dot - x_dot_pred)
            self._take_fix(x, x_dot, w, port_offset, obs)
            self._healthy += 1
            # the track proves itself for as long as it was lost, up to resume_s
            prove = self.g.resume_s if self.retreating else min(self.g.resume_s, self._lost_s)
            # a retreat resumes no closer than the commit range: from nearer, the approach cannot
            # reach the capture speed before contact (module docstring)
            inside = self.retreating and self.port(w)[0][2] < self.g.commit_range_m
            if self._avoided and (self._healthy * self.dt < prove - 1e-9 or inside):
                self.mode = "avoid"  # hold on fresh fixes until then
            else:
                self.mode = "nominal"
                self._avoided = False
                self.retreating = False
                self._lost_s = 0.0
            self._lost = 0
            self._pl = 0.0
            self._degraded_commit = False
            return self.mode
        self._healthy = 0
        if degraded and not self.has_fix and x_dot is not None and valid[_VEL] > 0.5:
            # no healthy pose yet: a degraded one is still the best state to brake and back away on
            self._take_fix(x, x_dot, w, port_offset, obs)
        if not self.has_fix:
            self.mode = "blind"
            return self.mode
        if degraded:
            assert x is not None
            # the degraded estimate's distance along the docking axis replaces the dead-reckoned one
            xr, xr_dot = self.dr.state(w)
            xr[2] = x[2]
            if x_dot is not None and valid[_VEL] > 0.5:
                xr_dot[2] += self.g.k_fix_velocity * (x_dot[2] - xr_dot[2])
            self.dr.reset_to(xr, xr_dot, w)
            self._pl = float(obs[_S["protection_level"]][0])
        committed = self.mode == "commit" or (self.mode == "nominal" and self._committable(w))
        if committed and (not degraded or self._degraded_commit or self._captured_within_bound(w)):
            self._degraded_commit = self._degraded_commit or degraded  # latched like a loss's
            self.mode = "commit"
            return self.mode
        if self.mode in ("nominal", "commit") and self.port(w)[0][2] <= self.g.commit_range_m:
            self.retreating = True  # abort: no hold this close to the port
        self._lost += 1
        self._lost_s = max(self._lost_s, self._lost * self.dt)
        if self._lost * self.dt >= self.g.hold_s - 1e-9:
            self.retreating = True
        self.mode = "avoid"
        self._avoided = True
        return self.mode

    def _take_fix(
        self, x: FloatArray, x_dot: FloatArray, w: FloatArray, port_offset: FloatArray | None,
        obs: npt.NDArray[np.floating],
    ) -> None:
        self.dr.fix(x, x_dot, w)
        self.has_fix = True
        self._since_fix_s = 0.0
        self._pl_fix = float(obs[_S["protection_level"]][0])
        self._port_offset = np.zeros(3) if port_offset is None else np.asarray(port_offset, float)

    def _committable(self, w: FloatArray) -> bool:
        """The last healthy state (one step on) may coast into contact (module docstring)."""
        g = self.g
        p, p_dot = self.port(w)
        closing = -float(p_dot[2])
        return bool(
            0.0 < p[2] <= g.commit_range_m
            and float(np.hypot(p[0], p[1])) <= g.commit_lateral_m
            and self.envelope[0] <= closing <= self.envelope[1]
            and float(np.hypot(p_dot[0], p_dot[1])) <= g.commit_lateral_speed
        )

    def _captured_within_bound(self, w: FloatArray) -> bool:
        """A degraded pose closer than the avoidance law can stop from (``closing / kv``) with the
        port bounded inside the capture envelope's lateral tolerance (``lateral_max_m``) by the
        pose's protection level or by the last healthy fix's, grown over the time since it and
        the time to contact at ``commit_lateral_speed`` (module docstring)."""
        if self.lateral_max_m is None:
            return False
        p, p_dot = self.port(w)
        closing = -float(p_dot[2])
        if closing <= 0.0 or p[2] > closing / self.g.kv:
            return False
        coast_s = self._since_fix_s + max(float(p[2]), 0.0) / closing
        bound = min(self._pl, self._pl_fix + self.g.commit_lateral_speed * coast_s)
        return float(np.hypot(p[0], p[1])) + bound <= self.lateral_max_m

    # ------------------------------------------------------------------ law
    def accel(self, obs: npt.NDArray[np.floating], hold_m: float | None = None,
              inertial: bool = False) -> FloatArray:
        """Body acceleration [m/s^2] of the current ``avoid`` or ``commit`` mode (before the
        thrust limit, which should scale the vector as a whole).

        Args:
            obs: the observation (for the gyro).
            hold_m: hold distance along the axis [m] (default ``hold_range_m``).
            inertial: hold (or retreat) the reference point still in the inertial frame rather
                than in the turning body frame: the speed loop works on the point's inertial
                velocity relative to the chaser, with no rotating-frame terms (a chaser that has
                stopped turning with the target; a body-frame hold would keep it circling at
                whatever rate it is left with).
        """
        w = obs[_S["chaser_rate_body"]].astype(np.float64)
        x, x_dot = self.dr.state(w)
        # the rotating body frame's Coriolis and centripetal terms (a frame constant in LVLH turns
        # at n: its CW terms are left to the speed loop)
        if inertial and self.model is None:
            x_dot = x_dot + np.cross(w, x)
            frame = np.zeros(3)
        else:
            frame = np.zeros(3) if self.model is not None else (
                -2.0 * np.cross(w, x_dot) - np.cross(w, np.cross(w, x)))
        if self.mode == "commit":
            return frame
        g = self.g
        hold = (g.hold_range_m if hold_m is None else hold_m) + self._pl
        if self.axis == "dock":
            u = np.array([0.0, 0.0, 1.0])
            s = float((x + self._port_offset - self.d)[2])
        else:
            s = float(np.linalg.norm(x))
            u = x / max(s, 1e-9)
        v_open = float(np.clip(g.k_hold * (hold - s), 0.0, g.v_retreat)) if self.retreating else 0.0
        if self._degraded_now and s > hold:  # measured along the axis: close to the hold point
            v_open = -min(g.k_hold * (s - hold), g.v_degraded_close)
        return g.kv * (x_dot - v_open * u) + frame

    def applied(self, a_body: FloatArray) -> None:
        """Record the body acceleration [m/s^2] the returned action commands (after limits)."""
        self._a_prev = np.asarray(a_body, dtype=np.float64).copy()
