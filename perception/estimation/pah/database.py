"""The PAH database of one target: :class:`PAHDatabase`, a facade over the package's stages.

Its tables are built by :mod:`.build`, written and read by :mod:`.fileio`, traversed by
:mod:`.polygons`; :meth:`PAHDatabase.localize` is :mod:`.search`, :meth:`~PAHDatabase.localize_scans`
:mod:`.multiscan`, :meth:`~PAHDatabase.verify_poses` :mod:`.verify` and
:meth:`~PAHDatabase.near_symmetries` :mod:`.symmetry`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from perception.config import ICPConfig, PAHConfig
from perception.estimation.registration import ModelCloud, RegistrationResult
from perception.sensing.pointcloud import PointCloud
from perception.targets import TargetModel

from . import fileio, multiscan, polygons, search, symmetry, verify
from .build import build_tables
from .constraint import PoseConstraint
from .hypotheses import _Hypothesis, _Scan
from .poses import FloatArray, IntArray


class PAHDatabase:
    """PAH reference database of one target, and the runtime localization that uses it.

    Attributes:
        target: the target model (needed by :meth:`localize` for the fit check and ICP), or None
            for a database loaded without its target (see :meth:`attach`).
        config: the PAH settings it was built with.
        model_hash: the geometry hash of the target it was built on.
        target_name: the target's name.
        points: (M, 3) sparse model points ``S`` [m], target frame.
        normals: (M, 3) their unit outward normals.
        coverage_m: 90th percentile of the distance from a surface point to the nearest ``s_i``
            [m]: how far a scan point may be from its match in ``S``.
        seg_i, seg_j, seg_len: the length table: undirected segments (i < j) sorted by length [m].
        bin_ptr: (B + 1,) offsets into the sorted segments of each ``length_bin_m`` bin.
        dist: (M, M) the connectivity table: ``dist[i, j] = |s_i - s_j|`` [m].
    """

    def __init__(
        self,
        *,
        config: PAHConfig,
        model_hash: str,
        target_name: str,
        points: FloatArray,
        normals: FloatArray,
        coverage_m: float,
        seg_i: IntArray,
        seg_j: IntArray,
        seg_len: FloatArray,
        bin_ptr: IntArray,
        dist: FloatArray,
        target: TargetModel | None = None,
    ) -> None:
        self.config = config
        self.model_hash = model_hash
        self.target_name = target_name
        self.points = points
        self.normals = normals
        self.coverage_m = float(coverage_m)
        self.seg_i, self.seg_j, self.seg_len = seg_i, seg_j, seg_len
        self.bin_ptr = bin_ptr
        self.dist = dist
        self._cluster_cache: dict[float, tuple[IntArray, int]] = {}
        self._rows_cache: tuple[IntArray, FloatArray, FloatArray, float] | None = None
        self.max_length_m = float(seg_len[-1]) if seg_len.size else 0.0
        self.target: TargetModel | None = None
        if target is not None:
            self.attach(target)

    def __repr__(self) -> str:
        return (
            f"PAHDatabase(target={self.target_name!r}, points={self.points.shape[0]}, "
            f"segments={self.seg_len.shape[0]}, polygon_size={self.config.polygon_size})"
        )

    # -- offline --------------------------------------------------------------------------------
    @classmethod
    def build(
        cls, target: TargetModel, config: PAHConfig | None = None, seed: int = 0
    ) -> PAHDatabase:
        """Build the reference database of a target (seed 000 section 3.1.1).

        Args:
            target: the target model (library target or any loaded mesh).
            config: PAH settings; defaults when None.
            seed: seed of the deterministic surface sampling and subsampling.

        Returns:
            The database, holding a reference to ``target``.

        Raises:
            ValueError: ``target`` is not a TargetModel, ``config`` not a PAHConfig, or the mesh has
                no surface.
        """
        return cls(**build_tables(target, config, seed), target=target)

    def attach(self, target: TargetModel) -> None:
        """Attach the target the database was built on (its geometry hash must match).

        Raises:
            ValueError: not a TargetModel, or a target with different geometry.
        """
        if not isinstance(target, TargetModel):
            raise ValueError(f"target is a {type(target).__name__}; expected a TargetModel")  # noqa: TRY004
        if target.model_hash != self.model_hash:
            raise ValueError(
                f"target {target.name!r} has model hash {target.model_hash[:12]}...; this PAH "
                f"database was built on {self.target_name!r} ({self.model_hash[:12]}...)"
            )
        self.target = target

    def save(self, path: str | Path) -> Path:
        """Write the database to ``path`` (``.npz`` appended if missing; no pickles).

        Returns:
            The path written.
        """
        return fileio.save_database(self, path)

    @classmethod
    def load(cls, path: str | Path, target: TargetModel | None = None) -> PAHDatabase:
        """Read a database written by :meth:`save`.

        Every entry is checked before use: each ``.npy`` header (dtype, shape, size against the
        archive) before its data is read, so a hostile header cannot make the loader allocate;
        then the values (finite, indices in range, the length table sorted and consistent with
        the connectivity table, ``bin_ptr`` the exact offsets of the length bins).

        Args:
            path: the ``.npz`` file.
            target: the target to attach; its geometry hash must match the database's.

        Raises:
            FileNotFoundError: no such file.
            PAHFileError: (a ValueError) not a PAH database, another format version, a corrupt
                file, or a target whose geometry differs from the one the database was built on.
                The message is one line naming the file (and the entry and its problem).
        """
        return fileio.load_database(cls, path, target)

    # -- runtime: polygon matching ---------------------------------------------------------------
    def match_polygon(
        self,
        Q: npt.ArrayLike,
        tolerance_m: float,
        rng: np.random.Generator,
        R_nominal: npt.ArrayLike | None = None,
        direction_tol_rad: float | None = None,
        *,
        constraint: PoseConstraint | None = None,
        rays: npt.ArrayLike | None = None,
        merge_m: float | None = None,
    ) -> IntArray:
        """All model polygons whose pairwise distances match a scan polygon's (partial traversal).

        The first edge comes from the length table, each further vertex from the banded rows of
        the connectivity table, and partial matches are pruned as early as they can be judged
        (direction, corridor, visibility, merging): :func:`.polygons.match_polygon`.

        Args:
            Q: (N, 3) scan polygon [m], sensor frame.
            tolerance_m: distance tolerance per edge [m].
            rng: draws the subset kept when a level exceeds ``max_candidates``.
            R_nominal: (3, 3) nominal attitude for direction pruning (constrained search).
            direction_tol_rad: angle [rad] the rotated model edge ``R_nominal (s_k - s_0)`` may make
                with the scan edge ``q_k - q_0`` (the attitude tolerance; widened here by the length
                tolerance). Both or neither of ``R_nominal`` and this.
            constraint: approach corridor; implies the direction pruning with its nominal attitude
                and tolerance unless those are given.
            rays: (N, 3) unit ray directions of the scan vertices, sensor frame.
            merge_m: merge distance [m] of partial-match poses (None: no merging).

        Returns:
            (K, N) model-point indices, row k matching ``Q`` vertex by vertex.
        """
        return polygons.match_polygon(
            self, Q, tolerance_m, rng, R_nominal, direction_tol_rad, constraint=constraint,
            rays=rays, merge_m=merge_m,
        )

    # -- runtime: localization ---------------------------------------------------------------------
    def localize(
        self,
        points: npt.ArrayLike,
        rng: np.random.Generator,
        constraint: PoseConstraint | None = None,
        sigma: float | npt.ArrayLike | None = None,
        max_time_s: float | None = None,
        directions: npt.ArrayLike | None = None,
        *,
        search_points: int | None = None,
    ) -> RegistrationResult:
        """Find the target pose in a scan without an initial guess (seed 000 section 3.1.2).

        For each polygon: match it, fit a pose per match, drop mirror images, back-facing and
        (constrained) out-of-corridor poses, precheck the survivors on a decimated scan, check the
        best few on the whole scan (or the ``search_points`` subset), and polish the distinct
        best ones by a short ICP (one start per basin; on the subset, if any) scored on the
        whole scan, surface fit and free space (so that near-symmetric alternatives are
        compared, not the first one taken); the leader's near-symmetric alternatives are
        verified too. It stops when a verified leader scores ``accept_fitness`` with (almost) no
        free-space violation, or the polygon or time budget is spent; the best hypothesis, and
        runners-up in other basins, are then refined by a full ICP and the best verified one wins.

        Args:
            points: (N, 3) scan points [m], sensor frame (non-finite rows are ignored).
            rng: the only source of randomness (polygon seeds, decimation, candidate caps).
            constraint: approach corridor; candidates outside it are dropped before any fit check.
            sigma: range noise 1-sigma [m], a float or (N,) per point; default 0.01 m.
            max_time_s: wall-clock budget [s], checked before each polygon; when it runs out the
                best hypothesis so far is refined and returned with ``converged=False`` unless it
                explains the scan. None: :data:`DEFAULT_TIME_BUDGET_S` unconstrained,
                :data:`DEFAULT_CONSTRAINED_TIME_BUDGET_S` with a constraint; ``math.inf``: none.
                A budget makes the result depend on the machine's speed when it runs out.
            directions: (N, 3) measured ray directions [sensor frame] (``PointCloud.directions``);
                default: the lines of sight ``points / |points|``. Every ICP matches points to
                the face their ray crosses, and the free-space test casts these rays.
            search_points: when the scan has more points, the fit check of the best matches and
                the short screening ICPs (the stages whose cost grows with the scan) run on a
                random subset of this many points (drawn from ``rng``); polygons are picked from,
                and every hypothesis is verified and the final ICP run on, all the points. Meant
                for scans pooled in a corridor (:meth:`localize_scans`), where one scan's worth of
                points finds the candidates and the rest tell them apart and refine the winner.
                None: all points everywhere.

        Returns:
            The ICP-refined :class:`RegistrationResult` of the best hypothesis; ``iterations`` is
            the ICP's. ``reason`` is empty when its score reached ``accept_fitness`` (inside the
            corridor, if any), otherwise it says why not. A scan too small or degenerate to
            localize, or one no polygon matched, gives ``RegistrationResult.failure``.

        Raises:
            ValueError: points not (N, 3), ``rng`` not a Generator, a bad ``constraint``,
                ``sigma``, ``max_time_s``, ``directions`` or ``search_points``, or a database
                without a target.
        """
        return search.localize(self, points, rng, constraint, sigma, max_time_s, directions,
                               search_points=search_points)

    def localize_scans(
        self,
        scans: Sequence[PointCloud],
        rng: np.random.Generator,
        constraint: PoseConstraint | None = None,
        max_time_s: float | None = None,
    ) -> RegistrationResult:
        """Localize from several successive scans of the same relative pose (more data, one pose).

        Seed 000 section 3.1.2: "it is possible to repeat the process ... from newly acquired point
        clouds over time ... to increase the probability of success". The scans must see the
        target at one pose in one sensor frame (a station-keeping chaser and a target that does
        not turn appreciably over the scans, or scans already compensated for the motion): their
        points, noise and measured rays are pooled and localized as one cloud by
        :meth:`localize`: polygons are picked from the pooled cloud, and every hypothesis is
        verified (surface fit and free space) and the final ICP run on all of it. Two or three
        scans halve the pose noise of a sparse scan's ICP and sample more of the small features
        (antenna, port ring, nozzle) that tell a box-shaped body from its quarter and half turns.

        With a ``constraint``, the search's work per candidate, the fit check of the best matches
        and the short screening ICPs, runs on a random subset of the pooled points the size of
        the largest scan (``search_points`` of :meth:`localize`), so that K scans cost little more
        than one: the corridor leaves few candidates, all near the nominal attitude, and one
        scan's worth of points finds them; the pool then decides between them and refines the
        winner (acquisition benchmark, 3 scans, 200 cases per target: 100 % success either way;
        median 0.052 -> 0.038 s on the cubesat, 0.044 -> 0.033 s on CYGNSS). Unconstrained the
        whole pool is searched: there the screening ICPs on the subset ended in wrong basins (or
        the time budget ran out) more often, 97.5 % against 99.5 % success on the cubesat.

        Nothing here checks that the scans share one pose (the fit of a box turned by 15 deg
        between scans hardly drops): pool only scans the caller knows to be of one pose.

        Args:
            scans: one or more :class:`~perception.sensing.pointcloud.PointCloud` (``points``, ``sigma``,
                ``directions`` are used).
            rng, constraint, max_time_s: as for :meth:`localize` (the budget covers all scans).

        Returns:
            As :meth:`localize`; ``n_points`` counts the pooled points.

        Raises:
            ValueError: ``scans`` empty or not PointClouds, and everything :meth:`localize` raises.
        """
        return multiscan.localize_scans(self, scans, rng, constraint, max_time_s)

    def verify_poses(
        self, points: FloatArray, sigma: float | FloatArray, Ts: FloatArray,
        directions: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Fitness and score of K candidate poses on a scan, as PAH ranks its hypotheses.

        The score is the mean Gaussian likelihood of the point-to-plane residuals minus
        ``2 x`` (outlier fraction + free-space violation fraction): a point the pose leaves
        unexplained, or one measured behind the model's first surface on its ray, is evidence
        against it.

        Args:
            points: (n, 3) finite scan points [m], sensor frame.
            sigma: range noise, scalar or (n,) [m].
            Ts: (K, 4, 4) poses ``T_sensor_target``.
            directions: (n, 3) ray directions (default: the lines of sight).

        Returns:
            ``(fitness, score)``, each (K,).
        """
        if self.target is None:
            raise ValueError("verify_poses() needs the target: build() or load(path, target)")
        return verify.verify_poses(self.target, points, sigma, Ts, directions)

    def near_symmetries(self) -> FloatArray:
        """(S, 4, 4) rigid motions ``G`` of the target frame that nearly map the model onto itself.

        ``T @ G`` is a pose that a partial scan may fit about as well as ``T`` (the half turn of a
        two-winged bus about its port axis). Needs the database's target; cached on it.
        """
        if self.target is None:
            raise ValueError("near_symmetries() needs the target: build() or load(path, target)")
        return symmetry._near_symmetries(self.target, self.model_hash)

    # -- search stages a search reaches through the database ----------------------------------
    def _screen(
        self,
        scan: _Scan,
        starts: list[FloatArray],
        known: list[_Hypothesis],
        mc: ModelCloud,
        icp_cfg: ICPConfig,
        icp_scan: _Scan | None = None,
    ) -> list[_Hypothesis]:
        """Short ICPs from ``starts``, verified (:func:`.verify._screen`)."""
        assert self.target is not None
        return verify._screen(self.target, scan, starts, known, mc, icp_cfg, icp_scan)

    def _polish(self, scan: _Scan, h: _Hypothesis, mc: ModelCloud) -> None:
        """Full ICP of ``h``, verified, in place (:func:`.verify._polish`)."""
        assert self.target is not None
        verify._polish(self.target, scan, h, mc)
