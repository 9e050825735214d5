"""Tumbling-target synchronisation controller (6-DOF: body thrust + body torque).

The controller reads only the observation: the estimated port pose and rates in the chaser docking
frame (``port_position_dock`` ``p``, its body-frame rate ``p_dot``, ``q_dock_port``,
``omega_port_dock`` ``w_rel``), the range/bearing block and the chaser's own gyro ``w``; the chaser's
mass, thrust, torque and hull size come from the mission config. Everything is expressed in the
docking frame, whose axes are the chaser body axes (the dock sits at ``d`` on the body +z).

Phases (:attr:`SyncController.phase`):

``approach``
    Far from the target the port axis sweeps metres per second (a 10 deg nutation at 60 m), so the
    chaser does not follow it: it points its docking axis at the port (rate damped against the
    line-of-sight rate, roll rate matched to the port's spin) and closes along the line of sight
    on a glideslope down to ``sync_range_m``, nulling the transverse velocity. This phase works
    on the *inertial* relative velocity of the port seen from the chaser's centre of mass,
    ``p_dot + w x (p + d)``, so no rotating-frame term appears.
``sync``
    Attitude: in the approach corridor (below), match the port; outside it keep pointing the
    docking axis at the port as in ``approach`` (matching a port that faces away would turn the
    sensor off the target and lose the track). The error ``e = rotvec(R_dock_port R_aligned)``
    (``R_aligned = diag(1, -1, -1)``) and ``w_rel`` drive a rate-limited PD, with the port's
    inertial angular acceleration (Euler's torque-free equations at the estimated rate
    ``w + w_rel`` with the target's inertia, design data like the port's lever) as feed-forward.
    ``w_rel`` goes through a predictor-corrector that knows the torque just applied
    (``d/dt w_rel = alpha_port - alpha_chaser - w x w_rel``), which averages estimate noise
    without lagging the control.
    Translation: hold the dock on the *rotating* port axis at ``s`` ahead of the port, the point
    ``h = p + s u`` with ``u = R_dock_port e_z`` (``h = 0`` there). The hold point is fixed in the
    *target's* frame, so the error is differentiated there: ``h' = p_dot - w_rel x p + s_dot u``,
    which does not see the chaser's own attitude transients (differentiating in the body frame
    turned every rate mismatch into a translation error and, on a fast minimum-axis spin,
    saturated the thrust until the chaser fell off its circle). The dock at ``rho`` from the
    target's centre of mass (``rho = r_port - p``, the port's lever from the target's design data)
    needs the acceleration ``alpha_t x rho + w_t x (w_t x rho) - 2 w_t x h'`` of a point fixed in
    the rotating target (``w_t = w + w_rel``, ``alpha_t`` from Euler's equations), less the dock's
    own lever-arm acceleration about the chaser's centre of mass. This feed-forward is served
    first; the PD ``kd (h' + sat(lam h, v_max))`` gets what thrust is left on each axis.
    Thrust budget: a point fixed in the target's frame at ``r`` from its spin axis costs
    ``|w_t|^2 r`` of centripetal acceleration, and moving through that frame at ``v`` adds
    ``2 |w_t| v`` of Coriolis; ``v_max`` is what ``budget_fraction`` of the thrust leaves after the
    centripetal term (at most ``v_hold_max``, at least ``v_hold_min``). At 5 deg/s a 0.25 m/s
    transfer alone needs 0.04 m/s^2, two thirds of the thrust, and a chaser that overshoots its hold
    point outward then has nothing left to stop (it drifts out along the axis and falls off).
    Where even the centripetal term exceeds ``infeasible_fraction`` of the thrust the circle
    cannot be held: the chaser goes back to ``approach`` (inertial, no centripetal needed) and
    re-enters ``sync`` closer in.
    Outside a cone of ``approach_cone_deg`` about the port axis (widened by the hull radius),
    the desired velocity may not close on the target faster than ``lam`` times the distance to a
    keep-out sphere (the target's radius + the hull + ``keep_out_margin_m``): the chaser goes
    around the wings to a port that faces away.
``close``
    Once the attitude error, the relative rate and the hold error across the axis (all low-passed
    over ``metric_filter_s``) have stayed inside the matching thresholds for ``dwell_s``, ``s``
    slides to zero along the port axis on a glideslope ending at ``v_final`` (inside the capture
    envelope); it freezes (hold point) while any of them leaves a looser band, and the dwell
    restarts.
``safe``
    **Lost or degraded pose: never correct toward a stale pose, never coast into the target**
    (:mod:`agents.safety`, DESIGN.md "Integrity"). From the last healthy pose (all four pose
    blocks valid, not degraded) the controller dead-reckons the target's centre of mass (the port
    minus its lever, design data) from its own centre of mass, in free fall, with its own
    saturated thrust and the gyro's rotation. Torque is zero, so the chaser keeps the inertial
    rate it had (the synchronised spin is the best open-loop continuation and keeps the target
    near the boresight), and its thrust holds the dead-reckoned centre of mass fixed in the
    turning body frame (the centripetal ``-w x (w x x)`` and Coriolis ``-2 w x x'`` terms of that
    rate plus a speed loop): a synchronised chaser keeps turning about the target with it, on the
    circle it was on, as long as that circle needs at most ``infeasible_fraction`` of the thrust;
    beyond it the chaser stops turning and points at the dead-reckoned centre of mass, holding
    inertially (:meth:`SyncController._safe_alpha`). Along the line to the centre of mass it
    never closes in; when the loss outlasts ``safety.hold_s`` (or at once inside
    ``safety.commit_range_m``) it backs away at ``safety.v_retreat`` to the hold distance (the
    ``standoff_m`` hold point's, at least the keep-out sphere). A degraded pose's depth along the
    docking axis corrects the dead reckoning. A healthy pose lost in the last ``safety.commit_range_m`` on the axis at the
    envelope's closing speed coasts into contact in the turning frame, its torque the target's
    own angular acceleration (Euler's equations run open loop from the last fix) so that the
    relative rate stays matched (a degraded one there backs away). Before any pose (acquisition)
    a closing range rate is braked along the line of sight (bearing) when both are valid, else
    the chaser coasts. On a healthy pose again (for as long as it was lost, at most
    ``safety.resume_s``) after a hold that did not turn into a retreat, the controller picks up its
    phase, hold point and dwell where it stopped; after a retreat it re-enters ``approach`` or
    ``sync`` by range with the hold point back at ``standoff_m`` and must dwell again before
    closing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agents.bearing_guidance import returns_centroid, sensor_mount
from agents.lqr import loss_of_track_accel, saturate
from agents.safety import CollisionAvoidance, SafetyGains
from agents.safety import rotvec_matrix
from perception.config import MissionConfig
from perception.geometry import quat_to_matrix
from tridar_env.env import make_target, observation_slices

_S = observation_slices()
FloatArray = npt.NDArray[np.float64]

#: Port attitude in the docking frame when the two are mated: x along x, z against z.
R_ALIGNED = np.diag([1.0, -1.0, -1.0])


@dataclass
class SyncGains:
    """Tunables of :class:`SyncController` (SI units)."""

    sync_range_m: float = 4.0  # [m] dock-to-port distance at which approach hands over to sync
    standoff_m: float = 3.0  # [m] hold point on the port axis
    # approach (line-of-sight glideslope)
    approach_slope: float = 0.02  # [1/s] v_des = slope * (distance - sync_range)
    approach_v_max: float = 0.5  # [m/s]
    approach_v_min: float = 0.05  # [m/s] so that the hand-over range is crossed
    kv: float = 0.4  # [1/s] speed loops
    # sync / close translation: h_dot_des = -sat(lam * h, v_hold_max); a = kd (h_dot - h_dot_des)
    lam: float = 0.12  # [1/s]
    kd: float = 0.5  # [1/s]
    v_hold_max: float = 0.25  # [m/s]
    v_hold_min: float = 0.02  # [m/s]
    budget_fraction: float = 0.7  # of the thrust, centripetal + Coriolis of the hold transfer
    infeasible_fraction: float = 0.9  # centripetal alone beyond this: back to approach
    # closing along the port axis
    close_slope: float = 0.05  # [1/s] s_dot = -clip(slope * s, v_final, v_close_max)
    v_final: float = 0.07  # [m/s] closing speed at contact (envelope 0.05-0.10)
    v_close_max: float = 0.12  # [m/s]
    close_accel: float = 0.01  # [m/s^2] the hold point speeds up gently
    s_end: float = -0.3  # [m] the hold point runs past the port so contact happens at v_final
    # attitude: w_des = sat(lam * e, w_max); alpha = kd (w_rel + w_des) (+ feed-forward in sync)
    point_lam: float = 0.5  # [1/s] approach: pointing the docking axis at the port
    point_kd: float = 1.2  # [1/s]
    att_lam: float = 0.1  # [1/s] sync/close: lower bandwidth, the pose estimate is noisier
    att_kd: float = 0.6  # [1/s]  than the line of sight
    w_max: float = 0.1  # [rad/s]
    rate_gain: float = 0.3  # correction gain of the relative-rate predictor-corrector
    metric_filter_s: float = 2.0  # [s] low-pass of the errors judged for closing
    # matching thresholds to start closing (and looser ones to keep closing)
    att_ok_deg: float = 1.5
    rate_ok_deg_s: float = 0.08
    hold_ok_m: float = 0.04
    hold_rate_ok_m_s: float = 0.015
    dwell_s: float = 5.0
    loose: float = 2.0  # closing freezes when an error exceeds loose * its threshold
    brake_gain: float = 0.4  # [1/s] loss-of-track braking of a closing range rate (no fix yet)
    # an inertial hold (lost pose, circle beyond the thrust) dead-reckons the target's centre of
    # mass aided by the returns' centroid (bearing and range) and the range rate, per step:
    aid_position: float = 0.1  # share of the centroid's innovation taken into the position
    aid_velocity: float = 0.01  # [1/step] ... and into the velocity (innovation / step time)
    aid_rate: float = 0.2  # share of the range rate's innovation taken along the line of sight
    safety: SafetyGains = field(default_factory=SafetyGains)  # lost or degraded track
    # keep-out sphere about the target's centre of mass (target radius + hull + margin), left
    # only inside the approach cone about the port axis
    keep_out_margin_m: float = 0.3
    approach_cone_deg: float = 30.0


class SyncController:
    """Synchronise with a tumbling target's port, then close along its rotating axis.

    Args:
        cfg: the mission config (chaser mass, thrust, torque, hull and dock offset; the env step).
        gains: controller gains.

    Raises:
        ValueError: when the chaser is not 6-DOF (``dynamics.chaser.attitude='controlled'``) or
            does not thrust in its body frame.
    """

    def __init__(self, cfg: MissionConfig, gains: SyncGains | None = None) -> None:
        ch = cfg.dynamics.chaser
        if ch.attitude != "controlled":
            raise ValueError(
                f"dynamics.chaser.attitude={ch.attitude!r}; SyncController needs 'controlled' (6-DOF)"
            )
        if ch.thrust_frame != "body":
            raise ValueError(f"dynamics.chaser.thrust_frame={ch.thrust_frame!r}; expected 'body'")
        self.cfg = cfg
        self.g = gains or SyncGains()
        self.dt = float(cfg.env.frame_period_s * cfg.env.frame_skip)
        self.dry = ch.dry_mass_kg
        self.prop0 = ch.propellant_kg
        self.max_thrust = ch.max_thrust_n
        self.max_torque = ch.max_torque_nm
        # The chaser is modelled as a uniform cube of the hull's size (its own design data).
        self.inertia = (ch.dry_mass_kg + ch.propellant_kg) * (2.0 * ch.hull_radius_m) ** 2 / 6.0
        self.d = np.array(ch.dock_position_m, dtype=np.float64)  # dock origin, body frame [m]
        self.alpha_max = self.max_torque / self.inertia  # [rad/s^2] per axis
        # The port's lever about the target's centre of mass, port frame (the target's design data).
        target = make_target(cfg)
        T_tp = target.T_target_port
        self.port_lever = T_tp[:3, :3].T @ T_tp[:3, 3]
        self.R_port_target = T_tp[:3, :3].T
        self.target_inertia = np.asarray(target.inertia, dtype=np.float64)  # [kg m^2], body axes
        self.keep_out_m = target.radius + ch.hull_radius_m + self.g.keep_out_margin_m
        self.hull = ch.hull_radius_m
        # the sensor's mount in the body (the returns' centroid from the bearing and range)
        self.R_cs, self.t_cs = sensor_mount(ch)
        self._cone_tan = float(np.tan(np.radians(self.g.approach_cone_deg)))
        # hold distance between the centres of mass: the standoff hold point's, outside keep-out
        self.hold_com_m = max(
            float(np.linalg.norm(self.port_lever + [0.0, 0.0, self.g.standoff_m + self.d[2]])),
            self.keep_out_m,
        )
        env = cfg.env.envelope
        self.safety = CollisionAvoidance(
            self.dt, self.d, (env.axial_speed_min_m_s, env.axial_speed_max_m_s), self.g.safety,
            axis="radial", lateral_max_m=env.lateral_offset_max_m,
        )
        self.reset()

    def reset(self) -> None:
        """Forget the episode: phase, hold distance, dwell timer and filters."""
        self.phase = "approach"
        self.s = self.g.standoff_m
        self.s_dot = 0.0
        self.dwell = 0.0
        self._metrics: FloatArray | None = None  # low-passed (e, w_rel, h_perp, h_dot_perp)
        self._w_rel_f: FloatArray | None = None  # filtered relative rate (sync and close)
        self._alpha_applied = np.zeros(3)  # chaser angular acceleration of the last action
        self._match = np.inf  # worst low-passed matching error / its threshold
        # target attitude in the last fix's body frame and its body rate (sync/close phases)
        self._target: tuple[FloatArray, FloatArray] | None = None
        # (phase, s, s_dot, dwell, metrics) before a hold that has not turned into a retreat
        self._paused: tuple[str, float, float, float, FloatArray | None] | None = None
        self._stop_turning = False  # this hold or retreat points at the target (latched)
        self.safety.reset()

    # ------------------------------------------------------------------ helpers
    def _mass(self, obs: npt.NDArray[np.floating]) -> float:
        return self.dry + self.prop0 * float(obs[_S["fuel_fraction"]][0])

    def _port_alpha(self, w_t: FloatArray, R_dp: FloatArray) -> FloatArray:
        """The target's inertial angular acceleration, docking frame [rad/s^2].

        Torque-free: ``I dw/dt = -w x I w`` in the target's body axes (the same derivative in the
        inertial frame), from the estimated rate and the target's inertia. Differencing the
        estimated rate instead needs a low-pass whose lag, times the 3-4 m lever of the hold
        point, left centimetres of hold error on a nutating target.
        """
        R_dt = R_dp @ self.R_port_target  # target axes in the docking frame
        wb = R_dt.T @ w_t
        return R_dt @ np.linalg.solve(self.target_inertia, -np.cross(wb, self.target_inertia @ wb))

    def _filter_rate(self, w: FloatArray, w_rel: FloatArray, alpha_t: FloatArray) -> FloatArray:
        """Relative rate through a predictor-corrector that knows the torque just applied.

        ``d/dt w_rel = alpha_port - alpha_chaser - w x w_rel`` in the docking frame; the chaser's
        angular acceleration is its own command, so the prediction carries the control and the
        correction (gain ``rate_gain``) only has to average the measurement noise.
        """
        if self._w_rel_f is None:
            self._w_rel_f = w_rel.copy()
            return self._w_rel_f
        wf = self._w_rel_f
        pred = wf + (alpha_t - self._alpha_applied - np.cross(w, wf)) * self.dt
        self._w_rel_f = pred + self.g.rate_gain * (w_rel - pred)
        return self._w_rel_f

    # ------------------------------------------------------------------ the law
    def command(self, obs: npt.NDArray[np.floating]) -> tuple[FloatArray, FloatArray]:
        """Body acceleration [m/s^2] and body angular acceleration [rad/s^2] commands."""
        g = self.g
        valid = obs[_S["valid"]]
        w = obs[_S["chaser_rate_body"]].astype(np.float64)
        p = obs[_S["port_position_dock"]].astype(np.float64)
        p_dot = obs[_S["port_velocity_dock"]].astype(np.float64)
        R_dp = np.eye(3)
        if valid[5] > 0.5:
            R_dp = quat_to_matrix(obs[_S["q_dock_port"]].astype(np.float64))
        w_rel = obs[_S["omega_port_dock"]].astype(np.float64)
        # the safety monitor's reference point: the target's centre of mass from the chaser's
        x = x_dot = lever = None
        if valid[3] > 0.5 and valid[5] > 0.5:
            lever = R_dp @ self.port_lever
            x = p + self.d - lever
            if valid[4] > 0.5 and valid[6] > 0.5:
                x_dot = p_dot - np.cross(w_rel, lever)
        mode = self.safety.update(obs, x, x_dot, lever)
        if mode != "nominal":
            if self.phase != "safe":  # where a brief hold picks up again
                self._paused = (self.phase, self.s, self.s_dot, self.dwell, self._metrics)
            if self.safety.retreating:
                self._paused = None
            self.phase = "safe"
            self.dwell = 0.0
            self._metrics = None
            self._match = np.inf
            self._w_rel_f = None
            if mode == "blind":
                return loss_of_track_accel(obs, g.brake_gain), np.zeros(3)
            if mode == "commit":
                alpha = self._committed_alpha()
            else:
                self._target = None
                alpha = self._safe_alpha(obs, w)
                if self._stop_turning:
                    self._aid(obs, w)
            return self.safety.accel(obs, self.hold_com_m, inertial=self._stop_turning), alpha
        self._stop_turning = False

        alpha_t = self._port_alpha(w + w_rel, R_dp)
        dist = float(np.linalg.norm(p))

        if self.phase == "safe" and self._paused is not None:
            # a hold without a retreat: carry on where the chaser stopped
            self.phase, self.s, self.s_dot, self.dwell, self._metrics = self._paused
        self._paused = None
        if self.phase == "safe":
            # after a retreat (or from acquisition) the close starts again from the hold point: a
            # hold point left near the port would pull the chaser back in and stop it there
            self.phase = "approach" if dist > g.sync_range_m + 0.5 else "sync"
            self.s = g.standoff_m
            self.s_dot = 0.0
        if self.phase == "approach" and dist <= g.sync_range_m:
            self.phase = "sync"
            self.s = g.standoff_m
            self.s_dot = 0.0

        self._target = None
        if self.phase == "approach":
            self._w_rel_f = None
            return self._approach(p, p_dot, w, w_rel, dist)

        w_rel = self._filter_rate(w, w_rel, alpha_t)
        alpha_t = self._port_alpha(w + w_rel, R_dp)
        # the target's attitude and body rate at this fix, for a committed coast into contact
        R_dt = R_dp @ self.R_port_target
        self._target = (R_dt, R_dt.T @ (w + w_rel))
        # ---- attitude: match the port (rate-limited PD + feed-forward of its acceleration) once
        # in the approach corridor; outside it the port's attitude would turn the sensor off the
        # target (a port facing away is matched by looking away), so keep pointing at the port
        u = R_dp @ np.array([0.0, 0.0, 1.0])
        e = _rotvec(R_dp @ R_ALIGNED)
        if self.phase == "close" or self._in_corridor(p, u):
            w_des = _sat(g.att_lam * e, g.w_max)
            # what the torque limit lets through (the translation compensates the actual alpha)
            alpha = saturate((g.att_kd * (w_rel + w_des) + alpha_t) / self.alpha_max) * self.alpha_max
        else:
            alpha = self._point(p, p_dot, w, w_rel)
        # ---- translation: hold the point s ahead of the port on its axis, in the target's frame
        w_t = w + w_rel  # the target's inertial rate, body coordinates
        r_p = R_dp @ self.port_lever  # port relative to the target's centre of mass
        r_com = r_p - p - self.d  # the chaser's centre of mass from the target's
        a_lim = self.max_thrust / self._mass(obs)
        if (self.phase == "sync" and dist > g.sync_range_m + 0.5
                and _centripetal(w_t, r_com) > g.infeasible_fraction * a_lim):
            # the circle through here needs more than the thrust: close in inertially first
            # (forgetting the matching state: sync starts afresh at the hand-over range)
            self.phase = "approach"
            self.dwell = 0.0
            self._metrics = None
            self._match = np.inf
            return self._approach(p, p_dot, w, w_rel, dist)
        p_dot_t = p_dot - np.cross(w_rel, p)  # the port's velocity seen from the target's frame
        h = p + self.s * u
        h_dot = p_dot_t + self.s_dot * u
        # matching is judged across the axis: along it the hold point is allowed to move
        self._update_phase(e, w_rel, h - (h @ u) * u, h_dot - (h_dot @ u) * u)
        if self.phase == "close":
            v_goal = float(np.clip(g.close_slope * self.s, g.v_final, g.v_close_max))
            self.s_dot = max(self.s_dot - g.close_accel * self.dt, -v_goal)
        else:
            self.s_dot = 0.0  # hold point frozen
        if self.s <= g.s_end:
            self.s_dot = 0.0
        self.s += self.s_dot * self.dt
        h = p + self.s * u
        h_dot = p_dot_t + self.s_dot * u
        rho = r_p - p  # the dock relative to the target's centre of mass
        # The dock's acceleration that keeps it fixed in the target's rotating frame (centripetal,
        # Euler and Coriolis terms of the target's rotation), minus the dock's own lever-arm
        # acceleration about the chaser's centre of mass: the model part, served first.
        a_ff = (np.cross(alpha_t, rho) + np.cross(w_t, np.cross(w_t, rho))
                - 2.0 * np.cross(w_t, h_dot - self.s_dot * u)
                - np.cross(alpha, self.d) - np.cross(w, np.cross(w, self.d)))
        v_max = self._speed_budget(w_t, r_com, a_lim)
        h_dot_des = -self._keep_out(_sat(g.lam * h, v_max), p, u, r_p)
        a_fb = g.kd * (h_dot - h_dot_des)
        return _allocate(a_ff, a_fb, a_lim), alpha

    def _safe_alpha(self, obs: npt.NDArray[np.floating], w: FloatArray) -> FloatArray:
        """Body angular acceleration [rad/s^2] of a hold or retreat (module docstring, ``safe``).

        Zero while the circle the chaser's rate ``w`` draws about the dead-reckoned centre of mass
        needs at most ``infeasible_fraction`` of the thrust: the synchronised spin goes on. Beyond
        that the circle cannot be held, and a chaser still turning with the target flies off it
        (a flash track lost 7 m out at 5.9 deg/s: full thrust in a turning frame, out of bounds at
        120 m two minutes later), so from then until a healthy pose it stops turning with the
        target: its docking axis points at the dead-reckoned centre of mass, its spin about that
        line stopped, and the hold is flown in the inertial frame (``CollisionAvoidance.accel``'s
        ``inertial``), with the sensor on the target for the reacquisition.
        """
        x, x_dot = self.safety.dr.state(w)
        a_lim = self.max_thrust / self._mass(obs)
        if not self._stop_turning and _centripetal(w, x) <= self.g.infeasible_fraction * a_lim:
            return np.zeros(3)
        self._stop_turning = True
        return self._point(x - self.d, x_dot, w, -w)

    def _aid(self, obs: npt.NDArray[np.floating], w: FloatArray) -> None:
        """Correct the inertial hold's dead-reckoned centre of mass with what the sensor still
        measures without a pose: the returns' centroid (bearing and range, valid in search mode)
        through an alpha-beta filter (``aid_position``, ``aid_velocity``), and the range rate along
        the line of sight (``aid_rate``). The centroid is the centre of mass within the target's
        size, a bounded error; dead reckoning alone drifts without bound (a flash track lost 8 m
        out left the chaser opening at 0.26 m/s for seven minutes while it held a point that was
        not there, the target out of its field of view)."""
        valid = obs[_S["valid"]]
        if valid[0] < 0.5 or valid[1] < 0.5:
            return
        g = self.g
        c, _ = returns_centroid(obs, self.R_cs, self.t_cs)
        x, x_dot = self.safety.dr.state(w)
        innov = c - x
        x = x + g.aid_position * innov
        x_dot = x_dot + g.aid_velocity * innov / self.dt
        if valid[2] > 0.5:
            u = x / max(float(np.linalg.norm(x)), 1e-9)
            rr = float(obs[_S["range_rate"]][0])
            x_dot = x_dot + g.aid_rate * (rr - float(x_dot @ u)) * u
        self.safety.dr.reset_to(x, x_dot, w)

    def _committed_alpha(self) -> FloatArray:
        """Body angular acceleration [rad/s^2] that keeps a committed chaser turning with the
        target: the target's torque-free motion (Euler's equations) propagated open loop from the
        last fix, in the body frame the safety monitor propagates with the gyro."""
        if self._target is None:
            return np.zeros(3)
        R_0t, wb = self._target
        I = self.target_inertia
        wb_dot = np.linalg.solve(I, -np.cross(wb, I @ wb))
        R_0t = R_0t @ rotvec_matrix(wb * self.dt)
        wb = wb + wb_dot * self.dt
        self._target = (R_0t, wb)
        return self.safety.dr.R.T @ R_0t @ np.linalg.solve(I, -np.cross(wb, I @ wb))

    def _speed_budget(self, w_t: FloatArray, r_com: FloatArray, a_lim: float) -> float:
        """Fastest transfer speed through the target's frame [m/s] that the thrust budget allows
        at the chaser's centre of mass ``r_com`` (from the target's), see the module docstring."""
        g = self.g
        wn = float(np.linalg.norm(w_t))
        if wn < 1e-9:
            return g.v_hold_max
        v = (g.budget_fraction * a_lim - _centripetal(w_t, r_com)) / (2.0 * wn)
        return float(np.clip(v, g.v_hold_min, g.v_hold_max))

    def _in_corridor(self, p: FloatArray, u: FloatArray) -> bool:
        """The dock is in the approach corridor: ahead of the port (no deeper than the hull radius
        behind it) and within ``approach_cone_deg`` of its axis, widened by the hull radius."""
        ax = -float(p @ u)  # the dock ahead of the port along its axis
        lat = float(np.linalg.norm(p + ax * u))
        return ax >= -self.hull and lat <= self.hull + self._cone_tan * max(ax, 0.0)

    def _keep_out(self, v: FloatArray, p: FloatArray, u: FloatArray, r_p: FloatArray) -> FloatArray:
        """Limit the dock's desired velocity ``v`` (target frame) at the keep-out sphere.

        Outside the approach corridor (a cone about the port axis widened by the hull radius, so
        that the last centimetres and the estimate's noise there stay inside it) the chaser's
        centre of mass may close on the target's only as fast as ``lam`` times its distance to
        the sphere (pushed back out when inside): the way to a hold point on the far side of a
        slowly turning target goes around the wings, not across them. Inside the corridor the
        docking axis is the way in.
        """
        if self._in_corridor(p, u):
            return v
        rho = r_p - p - self.d  # chaser's centre of mass from the target's
        D = float(np.linalg.norm(rho))
        if D < 1e-9:
            return v
        e = rho / D
        v_min = -self.g.lam * (D - self.keep_out_m)
        vr = float(v @ e)
        return v + (v_min - vr) * e if vr < v_min else v

    def _point(self, p: FloatArray, p_dot: FloatArray, w: FloatArray, w_rel: FloatArray) -> FloatArray:
        """Angular acceleration that points the docking axis at the port: the line of sight's
        inertial rate held, the port's spin about it matched, the pointing error a rate-limited
        PD (body frame, rad/s^2)."""
        g = self.g
        los = p / max(float(np.linalg.norm(p)), 1e-6)
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(z, los)
        sin_e = float(np.linalg.norm(axis))
        e = axis / sin_e * np.arctan2(sin_e, float(z @ los)) if sin_e > 1e-12 else np.zeros(3)
        # Far out, work with the inertial relative velocity of the port seen from the chaser's
        # centre of mass (body coordinates): no rotating-frame terms to compensate.
        r = p + self.d
        v = p_dot + np.cross(w, r)
        # hold the line-of-sight's inertial rate, and match the port's spin about it
        w_los = np.cross(r, v) / max(float(r @ r), 1e-6)
        w_ref = (w_los - w) - ((w_los - w) @ los) * los + (w_rel @ los) * los
        alpha = saturate(g.point_kd * (w_ref + _sat(g.point_lam * e, g.w_max)) / self.alpha_max)
        return alpha * self.alpha_max

    def _approach(
        self, p: FloatArray, p_dot: FloatArray, w: FloatArray, w_rel: FloatArray, dist: float
    ) -> tuple[FloatArray, FloatArray]:
        g = self.g
        alpha = self._point(p, p_dot, w, w_rel)
        los = p / max(dist, 1e-6)
        r = p + self.d
        v = p_dot + np.cross(w, r)  # the port's inertial velocity seen from the centre of mass
        v_des = float(np.clip(g.approach_slope * (dist - g.sync_range_m),
                              g.approach_v_min, g.approach_v_max))
        v_los = float(v @ los)  # negative when closing
        v_perp = v - v_los * los
        a = g.kv * (v_los + v_des) * los + g.kd * v_perp
        return a, alpha

    def _update_phase(self, e: FloatArray, w_rel: FloatArray, h: FloatArray, h_dot: FloatArray) -> None:
        g = self.g
        x = np.concatenate([e, w_rel, h, h_dot])
        if self._metrics is None:
            self._metrics = x
        else:
            self._metrics += self.dt / (g.metric_filter_s + self.dt) * (x - self._metrics)
        m = self._metrics
        errs = (
            np.degrees(np.linalg.norm(m[0:3])) / g.att_ok_deg,
            np.degrees(np.linalg.norm(m[3:6])) / g.rate_ok_deg_s,
            float(np.linalg.norm(m[6:9])) / g.hold_ok_m,
            float(np.linalg.norm(m[9:12])) / g.hold_rate_ok_m_s,
        )
        worst = max(errs)
        self._match = worst
        if self.phase == "sync":
            self.dwell = self.dwell + self.dt if worst <= 1.0 else 0.0
            if self.dwell >= g.dwell_s - 1e-9:
                self.phase = "close"
        elif self.phase == "close" and worst > g.loose:
            self.phase = "sync"  # freeze the hold point where it is and dwell again
            self.dwell = 0.0

    def __call__(self, obs: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        a, alpha = self.command(obs)
        mass = self._mass(obs)
        thrust = a * mass / self.max_thrust
        w = obs[_S["chaser_rate_body"]].astype(np.float64)
        # isotropic chaser inertia: w x (I w) vanishes, kept for clarity of the model
        torque = self.inertia * alpha + np.cross(w, self.inertia * w)
        out = np.concatenate([saturate(thrust), saturate(torque / self.max_torque)])
        self.executed(out, obs)
        return out.astype(np.float32)

    def executed(self, action: npt.ArrayLike, obs: npt.NDArray[np.floating]) -> None:
        """Record ``action`` (6,) as the one flown (the controller's own, at the end of each
        call; or another policy's, while the controller labels its states alongside it: DAgger
        in :mod:`agents.pretrain`): the rate predictor and the safety layer's dead reckoning
        carry what was applied."""
        act = np.clip(np.asarray(action, dtype=np.float64).reshape(6), -1.0, 1.0)
        self._alpha_applied = act[3:] * self.max_torque / self.inertia
        self.safety.applied(act[:3] * self.max_thrust / self._mass(obs))


def _allocate(a_ff: FloatArray, a_fb: FloatArray, limit: float) -> FloatArray:
    """``a_ff + k a_fb`` with the largest ``k`` in [0, 1] that keeps every axis within ``limit``.

    The feed-forward (what keeps the chaser on its rotating hold point) is served first; scaling
    the sum as a whole would shrink the centripetal term too and let the chaser drift outward,
    which then needs more thrust. When the feed-forward alone exceeds the limit it is scaled down.
    """
    over = float(np.max(np.abs(a_ff))) / limit
    if over >= 1.0:
        return a_ff / over
    k = 1.0
    for f, b in zip(a_ff, a_fb):
        if b > 0.0:
            k = min(k, (limit - f) / b)
        elif b < 0.0:
            k = min(k, (-limit - f) / b)
    return a_ff + max(k, 0.0) * a_fb


def _centripetal(w: FloatArray, r: FloatArray) -> float:
    """``|w x (w x r)|``: the acceleration that keeps ``r`` fixed in a frame turning at ``w``."""
    return float(np.linalg.norm(np.cross(w, np.cross(w, r))))


def _sat(v: FloatArray, limit: float) -> FloatArray:
    n = float(np.linalg.norm(v))
    return v if n <= limit else v * (limit / n)


def _rotvec(R: FloatArray) -> FloatArray:
    """Rotation vector [rad] of a rotation matrix (log map)."""
    cos = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    ang = float(np.arccos(cos))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if ang < 1e-9:
        return 0.5 * v
    if np.pi - ang < 1e-6:
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(R).as_rotvec()
    return v * (ang / (2.0 * np.sin(ang)))
