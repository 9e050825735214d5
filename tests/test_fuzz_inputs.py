"""Fuzzing the inputs a user controls: config files, overrides, ``gym.make`` configs and actions.

Whatever comes in, the outcome is a valid config (or env), or a ``ValueError`` (``ConfigError`` is
one) whose message is one short line; never another exception, a hang or a NaN observation.
Hypothesis settings keep the file well under a minute.
"""

from __future__ import annotations

import math
import tempfile
import typing
import warnings
from datetime import timedelta
from pathlib import Path
from typing import Any

import annotated_types as at
import gymnasium as gym
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import BaseModel

import tridar_env  # registers the ids
from perception.config import MAX_NODES, MissionConfig, load_config, resolve_config

FUZZ = settings(
    deadline=timedelta(seconds=5),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    database=None,
)
IDS = tuple(tridar_env.ENV_IDS)


def _assert_one_line_refusal(exc: BaseException) -> None:
    assert isinstance(exc, ValueError), f"{type(exc).__name__}: {exc}"
    msg = str(exc)
    assert msg and "\n" not in msg and len(msg) < 2000, msg


def _leaves(model: type[BaseModel], prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """Every field path of a config model with its FieldInfo (sections as well as values)."""
    out = []
    for name, info in model.model_fields.items():
        path = (*prefix, name)
        out.append((path, info))
        for sub in getattr(info.annotation, "__args__", (info.annotation,)):
            if isinstance(sub, type) and issubclass(sub, BaseModel):
                out.extend(_leaves(sub, path))
    return out


LEAVES = _leaves(MissionConfig)


def _bounds(info: Any) -> tuple[float | None, float | None]:
    lo = hi = None
    for m in info.metadata:
        if isinstance(m, (at.Gt, at.Ge)):
            lo = m.gt if isinstance(m, at.Gt) else m.ge
        if isinstance(m, (at.Lt, at.Le)):
            hi = m.lt if isinstance(m, at.Lt) else m.le
    return lo, hi


# -------------------------------------------------------------------------------- strategies
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**30), 10**30),
    st.just(5000).map(lambda digits: 10**digits),  # past str()'s digit limit
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.binary(max_size=4),
    st.sampled_from(["truth", "tridar", "cw", "1.0", "1e300", "true", ""]),
)
KNOWN_KEYS = st.sampled_from(LEAVES).flatmap(
    lambda leaf: st.sampled_from(["__".join(leaf[0]), ".".join(leaf[0]), leaf[0][-1]])
)
KEYS = st.one_of(KNOWN_KEYS, st.text(max_size=10), st.sampled_from(["", "__", "env__", "a..b"]))
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.tuples(inner, inner, inner),
        st.dictionaries(st.one_of(KEYS, st.integers(), st.none()), inner, max_size=4),
    ),
    max_leaves=10,
)
OVERRIDES = st.dictionaries(st.one_of(KEYS, st.integers(), st.none()), VALUES, max_size=5)


@st.composite
def plausible_value(draw: st.DrawFn, info: Any) -> Any:
    """A value near a field's default or its bounds (valid more often than not)."""
    default = info.default
    if typing.get_origin(info.annotation) is typing.Literal:
        return draw(st.sampled_from(typing.get_args(info.annotation)))
    lo, hi = _bounds(info)
    if isinstance(default, bool) or not isinstance(default, (int, float)):
        return draw(st.one_of(st.just(default), VALUES))
    choices = [st.just(default)]
    for b in (lo, hi):
        if b is not None:
            choices.append(st.just(b))
    if lo is not None and hi is not None:
        choices.append(st.floats(float(lo), float(hi)))
        if isinstance(default, int):
            choices.append(st.integers(math.ceil(lo), math.floor(min(hi, 10**9))))
    return draw(st.one_of(*choices))


@st.composite
def plausible_overrides(draw: st.DrawFn) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for _ in range(draw(st.integers(1, 6))):
        path, info = draw(st.sampled_from(LEAVES))
        if path == ("target", "name"):
            continue
        out["__".join(path)] = draw(plausible_value(info))
    if draw(st.booleans()):
        out.update(draw(OVERRIDES))
    return out


# -------------------------------------------------------------------------------- configs
@settings(FUZZ, max_examples=150)
@given(overrides=OVERRIDES, mission=st.sampled_from([None, "final_approach", "tumbling_target"]))
def test_random_overrides_validate_or_refuse_in_one_line(overrides: dict[Any, Any], mission: str | None) -> None:
    try:
        cfg = resolve_config(mission, overrides)
    except Exception as exc:  # noqa: BLE001  (the assertion says which)
        _assert_one_line_refusal(exc)
    else:
        assert isinstance(cfg, MissionConfig)


def _yaml_text(data: Any, anchors: bool) -> str:
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    if anchors:  # the same value twice through an alias
        text = f"base: &b {yaml.safe_dump(data, default_flow_style=True).strip()}\nagain: *b\n" + text
    return text


@settings(FUZZ, max_examples=100)
@given(
    data=st.one_of(OVERRIDES, VALUES),
    anchors=st.booleans(),
    raw=st.one_of(st.none(), st.binary(max_size=64), st.text(max_size=64)),
)
def test_random_config_files_load_or_refuse_in_one_line(data: Any, anchors: bool, raw: Any) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "fuzz.yaml"
        try:
            text = _yaml_text(data, anchors)
        except (yaml.YAMLError, ValueError, TypeError, RecursionError):
            return  # safe_dump cannot write it (a 5000-digit int); nothing to read
        if isinstance(raw, bytes):
            p.write_bytes(text.encode() + raw)
        else:
            p.write_text(text + (raw or ""), encoding="utf-8")
        try:
            cfg = load_config(p)
        except Exception as exc:  # noqa: BLE001
            _assert_one_line_refusal(exc)
        else:
            assert isinstance(cfg, MissionConfig)


@settings(FUZZ, max_examples=40)
@given(width=st.integers(1, 12), levels=st.integers(1, 12), under=st.sampled_from(["description", "unknown"]))
def test_alias_bombs_are_refused_short(width: int, levels: int, under: str) -> None:
    lines = ["l0: &l0 x"]
    for i in range(1, levels + 1):
        lines.append(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * width) + "]")
    lines.append(f"{under}: *l{levels}")
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "bomb.yaml"
        p.write_text("\n".join(lines) + "\n")
        with pytest.raises(ValueError) as info:
            load_config(p)
    _assert_one_line_refusal(info.value)
    expanded = sum(width**i for i in range(levels + 1))
    if expanded > MAX_NODES:
        assert "aliases expand" in str(info.value)


# -------------------------------------------------------------------------------- gym.make
@settings(FUZZ, max_examples=60)
@given(
    env_id=st.sampled_from(IDS),
    overrides=plausible_overrides(),
    seed=st.integers(0, 2**16),
    pattern=st.sampled_from([-1.0, 0.0, 1.0]),
    perception=st.sampled_from(["truth", "truth+noise"]),
)
def test_gym_make_with_random_configs_builds_a_finite_env_or_refuses(
    env_id: str, overrides: dict[Any, Any], seed: int, pattern: float, perception: str
) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a mesh-port warning is not the point here
        try:
            env = gym.make(env_id, config=overrides, perception=perception)
        except Exception as exc:  # noqa: BLE001
            _assert_one_line_refusal(exc)
            return
    u = env.unwrapped
    obs, _ = env.reset(seed=seed)
    assert np.isfinite(obs).all()
    for i in range(8):
        a = np.full(env.action_space.shape, pattern * (1 if i % 2 else -1), dtype=np.float32)
        obs, reward, terminated, truncated, _ = env.step(a)
        assert np.isfinite(obs).all() and math.isfinite(reward), (overrides, obs, reward)
        assert truncated == (i + 1 >= u.cfg.env.max_episode_steps)
        if terminated or truncated:
            break


# -------------------------------------------------------------------------------- actions
_ENV: dict[str, Any] = {}


def _truth_env() -> Any:
    if "env" not in _ENV:
        env = gym.make("TriDAR/FinalApproach-v0", perception="truth").unwrapped
        env.reset(seed=0)
        _ENV["env"] = env
    return _ENV["env"]


ARRAY_ACTIONS = hnp.arrays(
    dtype=st.one_of(
        hnp.floating_dtypes(), hnp.integer_dtypes(), hnp.boolean_dtypes(), hnp.complex_number_dtypes()
    ),
    shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4),
)
VALID_SHAPED = hnp.arrays(
    dtype=st.sampled_from([np.float16, np.float32, np.float64, np.int8, np.int64, np.uint16]),
    shape=st.sampled_from([(3,), (1, 3), (3, 1)]),
)
OBJECT_ACTIONS = st.one_of(
    st.lists(SCALARS, max_size=4),
    st.lists(st.lists(st.floats(), max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.floats(), max_size=3),
    SCALARS,
)


@settings(FUZZ, max_examples=250)
@given(action=st.one_of(ARRAY_ACTIONS, VALID_SHAPED, OBJECT_ACTIONS))
def test_random_actions_step_finite_or_refuse_in_one_line(action: Any) -> None:
    env = _truth_env()
    try:
        obs, reward, terminated, _, info = env.step(action)
    except Exception as exc:  # noqa: BLE001
        _assert_one_line_refusal(exc)
        return
    assert np.isfinite(obs).all() and math.isfinite(reward)
    assert obs.dtype == np.float32 and obs.shape == env.observation_space.shape
    assert 0 <= info["clipped_actions"] <= 3
    if terminated or env._steps > 200:
        env.reset(seed=0)


@settings(FUZZ, max_examples=60)
@given(action=st.one_of(ARRAY_ACTIONS, OBJECT_ACTIONS, hnp.arrays(np.float64, (2, 3))))
def test_random_actions_into_the_vector_env_step_finite_or_refuse(action: Any) -> None:
    if "vec" not in _ENV:
        _ENV["vec"] = gym.make_vec("TriDAR/FinalApproach-v0", num_envs=2, vectorization_mode="vector_entry_point",
                                   perception="truth")
        _ENV["vec"].reset(seed=0)
    envs = _ENV["vec"]
    try:
        obs, reward, *_ = envs.step(action)
    except Exception as exc:  # noqa: BLE001
        _assert_one_line_refusal(exc)
        return
    assert np.isfinite(obs).all() and np.isfinite(reward).all()
