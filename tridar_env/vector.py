"""``TruthVectorEnv``: many docking environments stepped as arrays, for fast training on truth.

Long module: one class whose physics, contact, rewards and observations must each repeat the
single environment's arithmetic row by row; split up, the parity would be spread over files.

The full TriDAR pipeline is a per-environment program (a scan, a registration, a filter), so it
vectorises across processes (``gymnasium.make_vec(..., vectorization_mode="async")``). The truth
stand-ins (``perception="truth"`` and ``"truth+noise"``) are a few dozen small matrix products per
step, and there Python's overhead per environment dominates: this class steps ``num_envs``
environments as ``(num_envs, ...)`` arrays instead, with the physics, rewards, terminations and
observations of :class:`~tridar_env.env.DockingEnv`, bit for bit (tests hold the two equal step
by step, seed by seed).

    >>> import gymnasium as gym, tridar_env
    >>> envs = gym.make_vec("TriDAR/FinalApproach-v0", num_envs=64,
    ...                     vectorization_mode="vector_entry_point", perception="truth")
    >>> obs, info = envs.reset(seed=0)
    >>> obs.shape
    (64, 36)

Environment ``i`` reset with ``seed=s`` is ``DockingEnv`` reset with ``seed=s + i`` (as in
Gymnasium's ``SyncVectorEnv``); a finished environment is reset by the next call to ``step``
(``AutoresetMode.NEXT_STEP``), which ignores its action and returns its first observation.

Bitwise parity: every row is computed with the single environment's floating-point operations in
its order. Its small matrix products go to BLAS, whose kernels fuse multiply-adds and sum in an
order of their own (which differs between CPU kernels), so no elementwise formula reproduces them.
But numpy's ``matmul`` over a stack calls BLAS once per item with that item's strides: a stack of
the single environment's operands, laid out as it lays them out (a transposed view stays a
transposed view, the 3x3 block of a 4x4 stays a block), rounds every row as its call does. A copied
transpose, ``einsum`` or an explicit sum of products does not. Its plain-float formulas
(``fast_cross``, ``fast_quat_to_matrix``, the propellant) are written out per element, and where it
uses Python's ``math.hypot``, ``atan2`` and ``acos`` (numpy's round differently in the last bit) so
does this class, element by element.

Scope: CW relative motion (``dynamics.orbit.model: cw``) and the ideal chaser attitude law (the
3-axis thrust action); every target attitude mode. Initial states come from the same
:meth:`World.reset <tridar_env.world.World.reset>` as the single environment, and a turning
target's attitude from the same integrator, so only the per-step arithmetic is batched.
``info`` holds arrays: ``t``, ``termination`` (``""`` while running), ``delta_v``,
``propellant_kg``, ``clipped_actions``, ``truth_r_lvlh``, ``truth_v_lvlh`` and the ``reward_*``
terms.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from scipy.spatial.transform import Rotation

from tridar_env.env import (
    CAUSES,
    OBS_DIM,
    DockingEnv,
    _resolve_config,
    as_action,
    envelope_excess,
    observation_slices,
)
from tridar_env.observers import truth_protection_level
from tridar_env.registration import mission_source
from tridar_env.world import ContactState, World, hull_touches_mesh

FloatArray = npt.NDArray[np.float64]

_SUPPORTED_PERCEPTION = ("truth", "truth+noise")
_S = observation_slices()
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


# ---------------------------------------------------------------------- the single env's products
# Each is one BLAS call per row (numpy's matmul loop), the call the single env makes for that row
# when the operands have its strides; ``_T`` is its ``.T`` (a view, never a copy).
def _T(M: FloatArray) -> FloatArray:
    """Transposed view of a stack of matrices, (..., i, j) -> (..., j, i)."""
    return np.swapaxes(M, -1, -2)


def _mv(M: FloatArray, v: FloatArray) -> FloatArray:
    """Rows of ``M @ v`` (gemv): (N, i, j) or (i, j) with (N, j) or (j,) -> (N, i)."""
    return np.matmul(M, v[..., None])[..., 0]


def _vm(v: FloatArray, M: FloatArray) -> FloatArray:
    """Rows of ``v @ M`` (gemv): (N, i) with (i, j) -> (N, j)."""
    return np.matmul(v[..., None, :], M)[..., 0, :]


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rows of ``a @ b`` for vectors (ddot): (N, i) with (N, i) -> (N,)."""
    return np.matmul(a[..., None, :], b[..., :, None])[..., 0, 0]


def _pose(R: FloatArray, r: FloatArray | None = None) -> FloatArray:
    """(N, 4, 4) transforms from (N, 3, 3) rotations and (N, 3) translations (``world._pose``)."""
    T = np.empty((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = 0.0 if r is None else r
    T[:, 3] = _LAST_ROW
    return T


# ---------------------------------------------------------------------- the single env's floats
def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise ``fast_cross``: (N, 3) x (N, 3) -> (N, 3)."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.subtract(a1 * b2, a2 * b1, out=out[:, 0])
    np.subtract(a2 * b0, a0 * b2, out=out[:, 1])
    np.subtract(a0 * b1, a1 * b0, out=out[:, 2])
    return out


def _quat_to_matrix(q: FloatArray) -> FloatArray:
    """Row-wise ``fast_quat_to_matrix``: (N, 4) scalar first -> (N, 3, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    R = np.empty((q.shape[0], 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = 1.0 - yy - zz, xy - wz, xz + wy
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = xy + wz, 1.0 - xx - zz, yz - wx
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = xz - wy, yz + wx, 1.0 - xx - yy
    return R


def _shepperd(R: FloatArray, tr: FloatArray, branch: int) -> FloatArray:
    """``fast_matrix_to_quat``'s unnormalised (w, x, y, z) of one of its four branches (0-2: the
    largest diagonal element, 3: the trace), for rows (N, 3, 3) with traces (N,)."""
    r00, r01, r02 = R[:, 0, 0], R[:, 0, 1], R[:, 0, 2]
    r10, r11, r12 = R[:, 1, 0], R[:, 1, 1], R[:, 1, 2]
    r20, r21, r22 = R[:, 2, 0], R[:, 2, 1], R[:, 2, 2]
    q = np.empty((R.shape[0], 4))
    if branch == 0:
        q[:, 0], q[:, 1], q[:, 2], q[:, 3] = r21 - r12, 1.0 - tr + 2.0 * r00, r10 + r01, r20 + r02
    elif branch == 1:
        q[:, 0], q[:, 1], q[:, 2], q[:, 3] = r02 - r20, r01 + r10, 1.0 - tr + 2.0 * r11, r21 + r12
    elif branch == 2:
        q[:, 0], q[:, 1], q[:, 2], q[:, 3] = r10 - r01, r02 + r20, r12 + r21, 1.0 - tr + 2.0 * r22
    else:
        q[:, 0], q[:, 1], q[:, 2], q[:, 3] = 1.0 + tr, r21 - r12, r02 - r20, r10 - r01
    return q


def _matrix_to_quat(R: FloatArray) -> FloatArray:
    """Row-wise ``fast_matrix_to_quat`` (Shepperd's method, its branch per row): (N, 3, 3) ->
    (N, 4) canonical, scalar first."""
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = r00 + r11 + r22
    # Its if/elif chain: the later assignments are the earlier branches.
    branch = np.full(R.shape[0], 3)
    branch[r22 >= tr] = 2
    branch[(r11 >= r22) & (r11 >= tr)] = 1
    branch[(r00 >= r11) & (r00 >= r22) & (r00 >= tr)] = 0
    kinds = np.unique(branch)
    if kinds.size == 1:  # the usual case: one branch for every row
        q = _shepperd(R, tr, int(kinds[0]))
    else:
        q = np.empty((R.shape[0], 4))
        for k in kinds.tolist():
            rows = branch == k
            q[rows] = _shepperd(R[rows], tr[rows], k)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    n = np.sqrt(w * w + x * x + y * y + z * z)
    n[w < 0.0] *= -1.0
    return q / n[:, None]


def _hypot(a: FloatArray, b: FloatArray) -> FloatArray:
    """``math.hypot`` per element (``numpy.hypot`` differs in the last bit)."""
    return np.array([math.hypot(x, y) for x, y in zip(a.tolist(), b.tolist())], dtype=np.float64)


def _atan2(a: FloatArray, b: FloatArray) -> FloatArray:
    """``math.atan2`` per element (numpy's vectorised ``arctan2`` differs in the last bit)."""
    return np.array([math.atan2(x, y) for x, y in zip(a.tolist(), b.tolist())], dtype=np.float64)


def _misalignment_deg(cosang: FloatArray) -> FloatArray:
    """``math.degrees(math.acos(c))`` per element, as ``World.contact``."""
    return np.array([math.degrees(math.acos(c)) for c in cosang.tolist()], dtype=np.float64)


class TruthVectorEnv(VectorEnv):
    """``num_envs`` docking environments with truth (or truth-plus-noise) perception, as arrays.

    Args:
        num_envs: environments stepped together.
        mission: mission name (the registered id's ``configs/missions`` file); set by
            ``gymnasium.make_vec``.
        config: a mission YAML path, ``MissionConfig`` or overrides dict (as ``DockingEnv``).
        perception: ``"truth"`` or ``"truth+noise"`` (the mission files default to ``"tridar"``,
            which this class does not batch).
        max_episode_steps: truncation (``make_vec`` passes the id's); default
            ``env.max_episode_steps``.
        **overrides: nested config values (``env__frame_skip=2``).

    Raises:
        ValueError: a perception, orbit model or chaser attitude mode it does not batch, naming
            the field and the value, and what to use instead.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 1,
        mission: str | None = None,
        config: Any = None,
        *,
        perception: str | None = None,
        max_episode_steps: int | None = None,
        **overrides: Any,
    ) -> None:
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs={num_envs!r}; expected an int >= 1")
        if perception is not None:
            overrides["env__perception"] = perception
        source, file_overrides = mission_source(mission, config)
        cfg = _resolve_config(source, {**file_overrides, **overrides})
        problems = []
        if cfg.env.perception not in _SUPPORTED_PERCEPTION:
            problems.append(
                f"env.perception={cfg.env.perception!r}; expected one of {_SUPPORTED_PERCEPTION} "
                "(pass perception='truth'; the pipeline vectorises with vectorization_mode='async')"
            )
        if cfg.dynamics.orbit.model != "cw":
            problems.append(f"dynamics.orbit.model={cfg.dynamics.orbit.model!r}; expected 'cw'")
        if cfg.dynamics.chaser.attitude != "ideal":
            problems.append(f"dynamics.chaser.attitude={cfg.dynamics.chaser.attitude!r}; expected 'ideal'")
        if cfg.env.task != "docking":
            problems.append(f"env.task={cfg.env.task!r}; expected 'docking'")
        if cfg.env.decision_schedule is not None:
            problems.append("env.decision_schedule is set; expected None (fixed-length steps)")
        if problems:
            raise ValueError(
                "TruthVectorEnv cannot batch this configuration: " + "; ".join(problems)
                + " (use gymnasium.make_vec(..., vectorization_mode='sync' or 'async') instead)"
            )
        self.cfg = cfg
        self.num_envs = num_envs
        # One single environment as the reference of spaces, mounts and bounds, and one World per
        # environment for its initial-state draws and (turning) target attitude. The constant
        # operands are theirs, with their layouts (see the module docstring).
        proto = DockingEnv(cfg)
        self.target = proto.target
        self.single_action_space = proto.action_space
        self.single_observation_space = proto.observation_space
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.max_episode_steps = int(max_episode_steps or cfg.env.max_episode_steps)
        self.worlds = [World(cfg, self.target) for _ in range(num_envs)]
        w0 = self.worlds[0]
        self.dt = w0.dt
        self.n = w0.n
        self._phi_T = w0._trans.phi.T
        self._gamma_T = w0._trans.gamma.T
        ch = cfg.dynamics.chaser
        self._ch = ch
        self._isp_g0 = w0.mass._isp_g0
        self._thrust_in_body = w0._thrust_in_body
        self._hull = w0._hull_radius
        self._reach = w0._mesh_reach
        self._T_chaser_sensor = w0.T_chaser_sensor
        self._t_chaser_sensor = w0._t_chaser_sensor
        self._T_chaser_dock = w0.T_chaser_dock
        self._R_target_dock = w0._R_target_dock
        self._T_target_port = w0._T_target_port
        self._n_lvlh = w0._n_lvlh
        self._T_dock_sensor = proto._T_dock_sensor
        self._obs_low = proto._obs_low64
        self._obs_high = proto._obs_high64
        self._att_mode = cfg.dynamics.target_attitude.mode
        observer = proto.observer
        self._sigmas = observer.sigmas
        self._noisy = observer.noisy
        self._ref_point = observer.ref_point  # None: the target origin
        self._port = observer.port
        self._integrity = observer.integrity
        self._gyro_sigma = math.radians(ch.gyro_noise_deg_s)
        # Applied at the port, the errors' protection level does not depend on the attitude.
        self._pl = (
            truth_protection_level(self._sigmas, np.eye(3), self._port, self._ref_point, self._integrity[0])
            if self._ref_point is not None else None
        )
        proto.close()
        N = num_envs
        self._rngs = [seeding.np_random(None)[0] for _ in range(N)]
        self._x = np.zeros((N, 6))
        self._prop = np.zeros(N)
        self._dv = np.zeros(N)
        self._t = np.zeros(N)
        self._steps = np.zeros(N, dtype=np.int64)
        self._bias = np.zeros((N, 3))
        self._R_lt = np.tile(np.eye(3), (N, 1, 1))
        self._w_t = np.zeros((N, 3))  # target angular velocity relative to LVLH, LVLH axes
        # The frames the target's attitude fixes (World.R_lvlh_chaser, T_lvlh_target, T_lvlh_port).
        self._R_lc = np.tile(np.eye(3), (N, 1, 1))
        self._T_lt = np.tile(np.eye(4), (N, 1, 1))
        self._T_lp = np.tile(np.eye(4), (N, 1, 1))
        self._err = np.zeros((N, 12))
        self._t_err = np.zeros(N)
        self._prev_distance = np.zeros(N)
        self._prev_lateral = np.zeros(N)
        self._autoreset = np.zeros(N, dtype=bool)
        self._ready = False

    # ------------------------------------------------------------------ reset
    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
        """Reset every environment; ``seed`` is an int (environment ``i`` gets ``seed + i``), a
        list of per-environment seeds, or None (fresh entropy on the first call)."""
        del options
        N = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * N
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(N)]
        else:
            seeds = list(seed)
            if len(seeds) != N:
                raise ValueError(f"seed has {len(seeds)} entries; expected num_envs={N}")
        for i, s in enumerate(seeds):
            if s is not None:
                self._rngs[i] = seeding.np_random(s)[0]
        self._reset_envs(np.arange(N))
        self._ready = True
        self._autoreset[:] = False
        obs = self._observe(first=np.ones(N, dtype=bool))
        info = self._info(np.zeros(N, dtype=np.int64), {}, np.zeros(N, dtype=np.int64))
        return obs, info

    def _reset_envs(self, idx: npt.NDArray[np.intp]) -> None:
        """Draw the initial states of environments ``idx`` (``World.reset``, in order)."""
        for i in idx.tolist():
            w = self.worlds[i]
            w.reset(self._rngs[i])
            self._x[i] = w.state
            self._prop[i] = w.mass.propellant_kg
            self._bias[i] = w._gyro_bias
            self._R_lt[i] = w.R_lvlh_target
            self._w_t[i] = w.omega_target_lvlh
        self._attitude_frames(idx)
        self._dv[idx] = 0.0
        self._t[idx] = 0.0
        self._steps[idx] = 0
        c = self._contact(idx)
        self._prev_distance[idx] = c["distance"]
        self._prev_lateral[idx] = c["lateral"]

    def _attitude_frames(self, idx: npt.NDArray[np.intp]) -> None:
        """The frames of environments ``idx`` that follow from the target's attitude alone."""
        R_lt = self._R_lt[idx]
        self._R_lc[idx] = np.matmul(R_lt, self._R_target_dock)  # the ideal law: docking faces port
        T_lt = _pose(R_lt)
        self._T_lt[idx] = T_lt
        self._T_lp[idx] = np.matmul(T_lt, self._T_target_port)

    # ------------------------------------------------------------------ step
    def step(
        self, actions: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float32], FloatArray, npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]]:
        if not self._ready:
            raise RuntimeError("TruthVectorEnv.step() called before reset(); call reset() first")
        N = self.num_envs
        a = as_action(actions, self.action_space.shape, "actions")
        clipped = np.count_nonzero(np.abs(a) > 1.0, axis=1)
        a = np.clip(a, -1.0, 1.0)
        fresh = self._autoreset.copy()
        run = np.flatnonzero(~fresh)
        if fresh.any():
            self._reset_envs(np.flatnonzero(fresh))
            clipped[fresh] = 0
        thrust = a * self._ch.max_thrust_n
        cause = np.zeros(N, dtype=np.int64)
        prop_before = self._prop.copy()
        # Each environment's contact at its last evaluation, which is at its final state (it stops
        # stepping once terminated): the rewards read it instead of recomputing it.
        last: dict[str, npt.NDArray[Any]] = {}
        active = run
        for _ in range(self.cfg.env.frame_skip):
            self._physics(active, thrust[active])
            cause[active], c = self._termination(active)
            for k, v in c.items():
                last.setdefault(k, np.zeros(N, dtype=v.dtype))[active] = v
            active = active[cause[active] == 0]
            if active.size == 0:
                break
        self._steps[run] += 1
        obs = self._observe(first=fresh)
        c_run = {k: v[run] for k, v in last.items()}
        terms = self._reward_terms(run, cause[run], prop_before[run] - self._prop[run], c_run)
        reward = np.zeros(N)
        for v in terms.values():
            reward[run] += v
        terminated = cause > 0
        # As gymnasium's TimeLimit: the step limit truncates whether or not the step also ended it.
        truncated = (self._steps >= self.max_episode_steps) & ~fresh
        self._autoreset = terminated | truncated
        info = self._info(cause, {k: self._scatter(run, v) for k, v in terms.items()}, clipped)
        return obs, reward, terminated, truncated, info

    def _scatter(self, idx: npt.NDArray[np.intp], v: FloatArray) -> FloatArray:
        out = np.zeros(self.num_envs)
        out[idx] = v
        return out

    def _physics(self, idx: npt.NDArray[np.intp], thrust: FloatArray) -> None:
        """One frame of ``World.step`` for environments ``idx``: thrust, propellant
        (``ChaserMass.apply``), CW (``CWPropagator.step``), attitude."""
        if idx.size == 0:
            return
        f = _mv(self._R_lc[idx], thrust) if self._thrust_in_body else thrust
        f = np.minimum(np.maximum(f, -self._ch.max_thrust_n), self._ch.max_thrust_n)
        f0, f1, f2 = f[:, 0], f[:, 1], f[:, 2]
        need = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2) / self._isp_g0 * self.dt
        prop = self._prop[idx]
        short = need > prop
        if short.any():
            f[short] = f[short] * (prop[short] / need[short])[:, None]
            need = np.where(short, prop, need)
        m_before = self._ch.dry_mass_kg + prop
        accel = f / m_before[:, None]
        self._prop[idx] = np.maximum(prop - need, 0.0)
        self._dv[idx] += np.sqrt(_dot(f, f)) / m_before * self.dt
        self._x[idx] = _vm(self._x[idx], self._phi_T) + _vm(accel, self._gamma_T)
        self._t[idx] += self.dt
        if self._att_mode != "lvlh_hold":
            for i in idx.tolist():
                w = self.worlds[i]
                w.target_attitude.step(self.dt)
                w._invalidate()
                self._R_lt[i] = w.R_lvlh_target
                self._w_t[i] = w.omega_target_lvlh
            self._attitude_frames(idx)

    # ------------------------------------------------------------------ truth geometry
    def _contact(self, idx: npt.NDArray[np.intp]) -> dict[str, npt.NDArray[Any]]:
        """``World.contact``, the dock-to-port distance (``DockingEnv._distance``) and whether
        the docking interface meets the port (``DockingEnv._port_contact``) for environments
        ``idx``. The lateral speed and misalignment are only read where it meets the port (the
        capture envelope), so only evaluated there (NaN elsewhere)."""
        r, v = self._x[idx, :3], self._x[idx, 3:]
        T_lp = self._T_lp[idx]
        T_ld = np.matmul(_pose(self._R_lc[idx], r), self._T_chaser_dock)
        p_port, p_dock = T_lp[:, :3, 3], T_ld[:, :3, 3]
        R_pl = _T(T_lp[:, :3, :3])
        dp = p_dock - p_port
        d = _mv(R_pl, dp)
        w = self._w_t[idx]  # the ideal chaser turns with the target
        vd = _mv(R_pl, (v + _cross(w, p_dock - r)) - _cross(w, p_port))
        ax, lat = d[:, 2], _hypot(d[:, 0], d[:, 1])
        port = (-self._hull <= ax) & (ax <= 0.0) & (lat <= self._hull)
        lateral_speed, misalignment = np.full(idx.size, np.nan), np.full(idx.size, np.nan)
        k = np.flatnonzero(port)
        if k.size:
            lateral_speed[k] = _hypot(vd[k, 0], vd[k, 1])
            cosang = np.clip(-_dot(T_ld[k][:, :3, 2], T_lp[k][:, :3, 2]), -1.0, 1.0)
            misalignment[k] = _misalignment_deg(cosang)
        return {
            "axial": ax, "lateral": lat, "closing": -vd[:, 2], "lateral_speed": lateral_speed,
            "misalignment": misalignment, "rate": np.zeros(idx.size),
            "distance": np.sqrt(_dot(dp, dp)), "port": port,
        }

    def _termination(self, idx: npt.NDArray[np.intp]) -> tuple[npt.NDArray[np.int64], dict[str, Any]]:
        """``DockingEnv._termination`` for environments ``idx``: 0, or 1 + index in ``CAUSES``; and
        the contact it was judged on."""
        env = self.cfg.env
        e = env.envelope
        c = self._contact(idx)
        ax, lat = c["axial"], c["lateral"]
        code = np.zeros(idx.size, dtype=np.int64)
        port = c["port"]
        inside = (
            (e.axial_speed_min_m_s <= c["closing"]) & (c["closing"] <= e.axial_speed_max_m_s)
            & (lat <= e.lateral_offset_max_m) & (c["lateral_speed"] <= e.lateral_speed_max_m_s)
            & (c["misalignment"] <= e.misalignment_max_deg) & (c["rate"] <= e.angular_rate_max_deg_s)
        )
        code[port] = np.where(inside[port], 1, 2)
        r = self._x[idx, :3]
        dist = np.sqrt(_dot(r, r))
        near = np.flatnonzero((code == 0) & (dist <= self._reach))
        if near.size:
            p_target = _mv(_T(self._T_lt[idx[near]][:, :3, :3]), r[near])
            code[near[hull_touches_mesh(self.target, p_target, self._hull)]] = 2
        code[(code == 0) & (dist > env.max_range_m)] = 3
        if env.corridor_half_angle_deg is not None:
            ahead = np.flatnonzero((code == 0) & (ax > 2.0))
            off = np.degrees(_atan2(lat[ahead], ax[ahead]))
            code[ahead[off > env.corridor_half_angle_deg]] = 5
        code[(code == 0) & (self._prop[idx] <= 0.0)] = 4
        return code, c

    def _reward_terms(
        self, idx: npt.NDArray[np.intp], cause: npt.NDArray[np.int64], fuel_used: FloatArray,
        c: dict[str, Any],
    ) -> dict[str, FloatArray]:
        """``DockingEnv._reward_terms`` for environments ``idx``, whose final contact is ``c``."""
        env = self.cfg.env
        rw, e = env.reward, env.envelope
        d, lat, ax = c["distance"], c["lateral"], c["axial"]
        progress = self._prev_distance[idx] - d
        lateral = self._prev_lateral[idx] - lat
        self._prev_distance[idx], self._prev_lateral[idx] = d, lat
        los = np.arctan2(lat, np.maximum(ax, 1e-3))
        dt = env.frame_period_s * env.frame_skip
        ax0 = np.maximum(ax, 0.0)
        v_max = env.speed_limit_floor_m_s + env.speed_limit_gain_s * ax0
        v_ref = np.minimum(0.5 * (e.axial_speed_min_m_s + e.axial_speed_max_m_s)
                           + env.speed_profile_gain_s * ax0, env.speed_profile_max_m_s)
        collision = np.where(cause == 2, -rw.collision, 0.0)
        port = (cause == 2) & c["port"]
        for k in np.flatnonzero(port).tolist():
            cs = ContactState(float(ax[k]), float(lat[k]), float(c["closing"][k]),
                              float(c["lateral_speed"][k]), float(c["misalignment"][k]), float(c["rate"][k]))
            collision[k] *= min(1.0, rw.near_miss + envelope_excess(cs, e))
        return {
            "reward_progress": rw.progress * progress,
            "reward_lateral": rw.lateral * lateral,
            "reward_alignment": -rw.alignment * (1.0 - np.cos(los)),
            "reward_speed_limit": -rw.speed_limit * np.maximum(0.0, c["closing"] - v_max),
            "reward_speed_profile": -rw.speed_profile * np.abs(c["closing"] - v_ref) * dt,
            "reward_time": np.full(idx.size, -rw.time * dt),
            "reward_fuel": -rw.fuel * fuel_used,
            "reward_success": np.where(cause == 1, rw.success, 0.0),
            "reward_collision": collision,
            "reward_corridor": np.where((cause == 3) | (cause == 5), -rw.corridor, 0.0),
        }

    # ------------------------------------------------------------------ observation
    def _draws(self, first: npt.NDArray[np.bool_]) -> tuple[FloatArray, FloatArray]:
        """Per environment, in ``DockingEnv``'s order: the 12 truth-noise normals, then the gyro's
        3 (each only when configured); the noise follows ``TruthObserver``'s Gauss-Markov law."""
        N = self.num_envs
        gyro = np.zeros((N, 3))
        if not (self._noisy or self._gyro_sigma > 0):
            return self._err, gyro
        tau = self.cfg.env.truth_noise_correlation_s
        for i, rng in enumerate(self._rngs):
            if self._noisy:
                w = rng.standard_normal(12)
                if first[i] or tau <= 0.0:
                    self._err[i] = w
                else:
                    phi = math.exp(-max(self._t[i] - self._t_err[i], 0.0) / tau)
                    self._err[i] = phi * self._err[i] + math.sqrt(1.0 - phi * phi) * w
                self._t_err[i] = self._t[i]
            if self._gyro_sigma > 0:
                gyro[i] = rng.normal(0.0, self._gyro_sigma, 3)
        return self._err, gyro

    def _sensor_truth(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``World.sensor_truth`` of every environment: ``T_sensor_target`` (N, 4, 4), the
        target's velocity and angular velocity in the sensor frame, and the chaser's LVLH
        angular velocity."""
        r, v = self._x[:, :3], self._x[:, 3:]
        R_lc = self._R_lc
        T_ls = np.matmul(_pose(R_lc, r), self._T_chaser_sensor)
        R_sl = _T(T_ls[:, :3, :3])
        T_sl = np.zeros_like(T_ls)  # fast_invert
        T_sl[:, :3, :3] = R_sl
        T_sl[:, :3, 3] = -_mv(R_sl, T_ls[:, :3, 3])
        T_sl[:, 3, 3] = 1.0
        T_st = np.matmul(T_sl, self._T_lt)
        w_t = self._w_t
        w_c = w_t  # the ideal chaser turns with the target
        v_s = v + _cross(w_c, _mv(R_lc, self._t_chaser_sensor))
        vel = _mv(R_sl, -v_s) - _cross(_mv(R_sl, w_c), T_st[:, :3, 3])
        omega = _mv(R_sl, w_t - w_c)
        return T_st, vel, omega, w_c

    def _observe(self, first: npt.NDArray[np.bool_]) -> npt.NDArray[np.float32]:
        """``DockingEnv._observation`` of ``TruthObserver``'s state vector of every environment
        (``state_from_truth``)."""
        N = self.num_envs
        T_st, vel, omega, w_c = self._sensor_truth()
        p = T_st[:, :3, 3].copy()
        R = T_st[:, :3, :3]
        err, gyro_noise = self._draws(first)
        if self._noisy:
            sp, sv, sa, sw = self._sigmas
            R_est = np.matmul(Rotation.from_rotvec(sa * err[:, 6:9]).as_matrix(), R)
            ref = self._ref_point
            if ref is None:
                p = p + sp * err[:, 0:3]
            else:
                p = p + _mv(R, ref) + sp * err[:, 0:3] - _mv(R_est, ref)
            R = R_est
            vel = vel + sv * err[:, 3:6]
            omega = omega + sw * err[:, 9:12]
        rng_m = np.sqrt(_dot(p, p))
        risk, al_m, al_range = self._integrity
        pl = self._pl if self._pl is not None else np.array(
            [truth_protection_level(self._sigmas, R[i], self._port, None, risk) for i in range(N)])
        port_s = p + _mv(R, self._port)
        al = al_m * np.maximum(1.0, np.sqrt(_dot(port_s, port_s)) / al_range)
        # DockingEnv._observation, from the state vector's quaternion.
        R_st = _quat_to_matrix(_matrix_to_quat(R))
        T_dp = np.matmul(np.matmul(self._T_dock_sensor, _pose(R_st, p)), self._T_target_port)
        R_ds = self._T_dock_sensor[:3, :3]
        r_port_s = _mv(R_st, self._T_target_port[:3, 3])
        obs = np.zeros((N, OBS_DIM))
        S = _S
        obs[:, S["mode_onehot"].start + 2] = 1.0  # tracking
        obs[:, S["valid"].start:S["valid"].stop - 1] = 1.0  # every field valid
        obs[:, S["valid"].stop - 1] = pl > al  # degraded
        obs[:, S["port_position_dock"]] = T_dp[:, :3, 3]
        obs[:, S["port_velocity_dock"]] = _mv(R_ds, vel + _cross(omega, r_port_s))
        obs[:, S["q_dock_port"]] = _matrix_to_quat(T_dp[:, :3, :3])
        obs[:, S["omega_port_dock"]] = _mv(R_ds, omega)
        obs[:, S["range"].start] = rng_m
        obs[:, S["range_rate"].start] = _dot(p, vel) / np.maximum(rng_m, 1e-9)
        b = S["bearing"].start
        obs[:, b] = _atan2(p[:, 0], p[:, 2])
        obs[:, b + 1] = _atan2(-p[:, 1], _hypot(p[:, 0], p[:, 2]))
        obs[:, S["fitness"].start] = 1.0
        fuel0 = self._ch.propellant_kg
        obs[:, S["fuel_fraction"].start] = self._prop / fuel0 if fuel0 > 0 else 0.0
        obs[:, S["time_fraction"].start] = self._steps / self.cfg.env.max_episode_steps
        # World.gyro: chaser_angular_velocity_body plus the bias (and the noise).
        w_body = _mv(_T(self._R_lc), w_c + self._n_lvlh)
        gyro = w_body + self._bias
        obs[:, S["chaser_rate_body"]] = gyro + gyro_noise if self._gyro_sigma > 0 else gyro
        obs[:, S["protection_level"].start] = pl
        obs[:, S["alert_limit"].start] = al
        np.clip(obs, self._obs_low, self._obs_high, out=obs)
        return obs.astype(np.float32)

    def _info(
        self, cause: npt.NDArray[np.int64], terms: dict[str, FloatArray], clipped: npt.NDArray[np.int64]
    ) -> dict[str, Any]:
        names = np.array(("",) + CAUSES, dtype=object)
        info: dict[str, Any] = {
            "t": self._t.copy(),
            "termination": names[cause],
            "delta_v": self._dv.copy(),
            "propellant_kg": self._prop.copy(),
            "clipped_actions": np.asarray(clipped, dtype=np.int64),
            "truth_r_lvlh": self._x[:, :3].copy(),
            "truth_v_lvlh": self._x[:, 3:].copy(),
        }
        info.update(terms)
        return info

    def close_extras(self, **kwargs: Any) -> None:
        del kwargs
        self.worlds = []


__all__ = ["TruthVectorEnv"]
