"""Seeded rollouts of every env id and perception mode, reduced to digests.

``python -m tests.rollout_digests`` prints them as JSON (to record ``tests/data/rollout_digests.json``
before a behaviour-preserving change); ``tests/test_rollout_digests.py`` compares.

A digest hashes the observations, rewards, terminations and the truth pose of each step, each
float rounded to 9 significant digits: a refactoring must leave them unchanged, while the last-bit
differences between BLAS kernels (``OPENBLAS_CORETYPE``) do not show.
"""

from __future__ import annotations

import hashlib
import json
import sys

import numpy as np

from tridar_env.registration import ENV_IDS as _IDS

ENV_IDS = tuple(_IDS)
PERCEPTIONS = ("truth", "truth+noise", "tridar", "flash")
STEPS = {"truth": 80, "truth+noise": 80, "tridar": 60, "flash": 40}


def _round(a: np.ndarray) -> bytes:
    a = np.asarray(a, dtype=np.float64)
    return np.array([float(f"{v:.9g}") for v in a.ravel()]).tobytes()


def rollout_digest(env_id: str, perception: str, seed: int = 7, steps: int | None = None) -> str:
    """SHA-256 of a seeded rollout with seeded random actions."""
    import gymnasium as gym

    import tridar_env  # noqa: F401  (registers the ids)

    env = gym.make(env_id, perception=perception)
    try:
        h = hashlib.sha256()
        obs, info = env.reset(seed=seed)
        h.update(_round(obs))
        rng = np.random.default_rng(seed)
        for _ in range(steps or STEPS[perception]):
            a = rng.uniform(-0.3, 0.3, size=env.action_space.shape).astype(env.action_space.dtype)
            obs, r, term, trunc, info = env.step(a)
            h.update(_round(obs))
            h.update(_round(np.array([r])))
            h.update(bytes([bool(term), bool(trunc)]))
            h.update(_round(info["truth_T_sensor_target"]))
            if term or trunc:
                obs, info = env.reset()
        return h.hexdigest()
    finally:
        env.close()


def all_digests() -> dict[str, str]:
    return {f"{e}|{p}": rollout_digest(e, p) for e in ENV_IDS for p in PERCEPTIONS}




#: Packages whose numerics the closed loop goes through: a new release of any of them (Embree's
#: ray hits through embreex, trimesh's mesh processing, scipy's KD-tree and rotations, OpenCV's
#: line detector) moves a seeded rollout past the 9th digit as surely as another BLAS kernel does
#: (a fresh environment that took trimesh 5.2 and embreex 4.4 changed 7 of the 24 digests).
NUMERIC_PACKAGES = ("numpy", "scipy", "trimesh", "embreex", "opencv-python-headless")


def package_versions() -> dict[str, str]:
    """Installed versions of :data:`NUMERIC_PACKAGES` (``"-"`` for one not installed)."""
    from importlib import metadata

    out = {}
    for name in NUMERIC_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "-"
    return out


#: SIMD levels, widest last: Embree (through embreex) picks its ray kernels by the widest the CPU
#: has, whatever OpenBLAS is told, and its hits round differently on each.
SIMD_LEVELS = ("sse4_2", "avx", "avx2", "avx512f")


def simd_level() -> str:
    """The widest of :data:`SIMD_LEVELS` this CPU lists (Linux ``/proc/cpuinfo``; ``"-"`` where
    it cannot be read). Two machines whose BLAS rounds alike (an AVX-512 EPYC told
    ``OPENBLAS_CORETYPE=Haswell`` and an AVX2 one) still differed on 7 of the 24 digests: their
    ray casts did."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            flags: set[str] = set()
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    break
    except OSError:
        return "-"
    have = [level for level in SIMD_LEVELS if level in flags]
    return have[-1] if have else "-"


def numerics_fingerprint() -> str:
    """The last bits of a few BLAS/LAPACK results of the kinds the pipeline uses, the versions of
    :data:`NUMERIC_PACKAGES` and the CPU's :func:`simd_level`: digests are recorded per
    fingerprint (another BLAS kernel, another release or another ray kernel rounds differently,
    and a closed loop over ICP and a filter carries that to the 9th digit within seconds)."""
    rng = np.random.default_rng(0)
    h = hashlib.sha256()
    for n in (3, 6, 12, 64):
        A = rng.normal(size=(n, n))
        B = rng.normal(size=(n, n))
        h.update((A @ B).tobytes())
        h.update(np.linalg.solve(A @ A.T + np.eye(n), B).tobytes())
        h.update(np.linalg.eigh(A @ A.T)[0].tobytes())
    P = rng.normal(size=(5000, 3))
    h.update((P @ rng.normal(size=(3, 3))).tobytes())
    h.update((P.T @ P).tobytes())
    h.update(json.dumps(package_versions(), sort_keys=True).encode())
    h.update(simd_level().encode())
    return h.hexdigest()[:16]


if __name__ == "__main__":
    entry = {"versions": package_versions(), "simd": simd_level(), **all_digests()}
    json.dump({numerics_fingerprint(): entry}, sys.stdout, indent=2)
    sys.stdout.write("\n")
