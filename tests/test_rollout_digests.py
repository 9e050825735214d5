"""Seeded rollouts of every env id and perception mode equal the digests recorded before the last
behaviour-preserving change (the perception/ restructuring): ``python -m tests.rollout_digests``
records them (see that module)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.rollout_digests import ENV_IDS, PERCEPTIONS, numerics_fingerprint, rollout_digest

RECORDED = json.loads((Path(__file__).parent / "data" / "rollout_digests.json").read_text())


@pytest.mark.parametrize("perception", PERCEPTIONS)
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_seeded_rollout_equals_the_recorded_digest(env_id: str, perception: str) -> None:
    fp = numerics_fingerprint()
    if fp not in RECORDED:
        pytest.skip(f"digests were recorded on other BLAS builds or package versions ({sorted(RECORDED)}), not {fp}")
    assert rollout_digest(env_id, perception) == RECORDED[fp][f"{env_id}|{perception}"]


def test_the_fingerprint_names_the_package_versions_it_was_recorded_with() -> None:
    """Each recorded set says which releases of the numerical packages made it, and the
    fingerprint changes with any of them (a new release is another build, not a regression)."""
    from tests import rollout_digests as rd

    for fp, entry in RECORDED.items():
        assert set(entry["versions"]) == set(rd.NUMERIC_PACKAGES), fp
        assert entry["simd"] in (*rd.SIMD_LEVELS, "-"), fp
    here = rd.numerics_fingerprint()
    real = rd.package_versions
    try:
        rd.package_versions = lambda: {**real(), "trimesh": "0.0.0"}  # type: ignore[assignment]
        assert rd.numerics_fingerprint() != here
    finally:
        rd.package_versions = real  # type: ignore[assignment]
    real_simd = rd.simd_level
    try:  # the same BLAS and releases on a CPU with other ray kernels are another build
        rd.simd_level = lambda: "avx2" if real_simd() != "avx2" else "avx512f"  # type: ignore[assignment]
        assert rd.numerics_fingerprint() != here
    finally:
        rd.simd_level = real_simd  # type: ignore[assignment]
