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
        pytest.skip(f"digests were recorded on other BLAS builds ({sorted(RECORDED)}), not {fp}")
    assert rollout_digest(env_id, perception) == RECORDED[fp][f"{env_id}|{perception}"]
