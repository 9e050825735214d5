"""Reading YAML: a bounded safe loader (file size, nesting, alias expansion and node count have
limits whatever the file holds; duplicate keys are refused) and one-line messages of its
errors."""

from __future__ import annotations

import re
import stat
from pathlib import Path
from typing import Any

import yaml

from perception.config.errors import ConfigError, short_repr

#: Largest config file read [bytes]; the shipped ones are a few kB.
MAX_FILE_BYTES = 1 << 20
#: Deepest nesting of mappings and sequences (a scalar counts as a level); configs use about 5.
MAX_NESTING = 32
#: Most values a document may hold with its aliases expanded (a billion-laughs file holds 10^9).
MAX_NODES = 20_000


class _LimitError(yaml.MarkedYAMLError):
    """A document refused for its size, nesting or aliases (not a syntax error)."""


class _ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and bounds nesting and node count while it
    composes (PyYAML's composer recurses once per level: 20,000 levels were a RecursionError)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):  # the anchored node again: neither deeper nor new
            return super().compose_node(parent, index)
        self._nodes += 1
        self._depth += 1
        try:
            mark = self.peek_event().start_mark
            if self._depth > MAX_NESTING:
                raise _LimitError(problem=f"nested deeper than {MAX_NESTING} levels", problem_mark=mark)
            if self._nodes > MAX_NODES:
                raise _LimitError(problem=f"more than {MAX_NODES} values", problem_mark=mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


# YAML 1.1 (PyYAML) reads ``1e-3`` as a string, which a number field now refuses; YAML 1.2 and every
# reader of a config take it for the number it looks like.
_ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _check_duplicate_keys(loader: _ConfigLoader, node: yaml.MappingNode) -> None:
    first: dict[Any, yaml.Node] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
            continue  # merge keys may repeat keys on purpose; a non-scalar key PyYAML refuses itself
        key = loader.construct_object(key_node)
        if key in first:
            raise yaml.constructor.ConstructorError(
                problem=f"duplicate key {short_repr(key)} (first at line "
                f"{first[key].start_mark.line + 1})",
                problem_mark=key_node.start_mark,
            )
        first[key] = key_node


def _check_document(loader: _ConfigLoader, root: yaml.Node) -> None:
    """Refuse a composed document whose aliases expand past :data:`MAX_NODES` values or
    :data:`MAX_NESTING` levels, or refer to themselves; and duplicate keys. Iterative, and each
    node is visited once: the expanded sizes are added up, never built."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        k = id(node)
        if done:
            on_path.discard(k)
            kids = _children(node)
            size[k] = 1 + sum(size[id(c)] for c in kids)
            depth[k] = 1 + max((depth[id(c)] for c in kids), default=0)
            if size[k] > MAX_NODES:
                raise _LimitError(
                    problem=f"aliases expand to more than {MAX_NODES} values", problem_mark=node.start_mark
                )
            if depth[k] > MAX_NESTING:
                raise _LimitError(
                    problem=f"aliases nest deeper than {MAX_NESTING} levels", problem_mark=node.start_mark
                )
            continue
        if k in size:
            continue
        if k in on_path:
            raise _LimitError(problem="an alias refers to its own anchor", problem_mark=node.start_mark)
        on_path.add(k)
        if isinstance(node, yaml.MappingNode):
            _check_duplicate_keys(loader, node)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node))


def parse_yaml(text: str) -> Any:
    """One YAML document with the safe loader, refused (``yaml.YAMLError``) when it nests deeper
    than :data:`MAX_NESTING`, expands past :data:`MAX_NODES` values or repeats a key."""
    loader = _ConfigLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_document(loader, node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line: the problem and where (PyYAML's own message spans several lines)."""
    if isinstance(exc, yaml.MarkedYAMLError):
        what = " ".join(str(x) for x in (exc.context, exc.problem) if x)
        mark = exc.problem_mark or exc.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        return " ".join(what.split())[:200] + where
    return " ".join(str(exc).split())[:200]


def _read_text(p: Path) -> str:
    """The UTF-8 text of a regular file of at most :data:`MAX_FILE_BYTES` (read no further)."""
    try:
        st = p.stat()
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except (OSError, ValueError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise ConfigError(f"config file {p} cannot be read: {why}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"config file {p} is a directory; expected a YAML file")
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"config file {p} is not a regular file (a device or a pipe); expected a YAML file")
    too_big = f"config file {p} is larger than {MAX_FILE_BYTES} bytes; expected a config of a few kB"
    if st.st_size > MAX_FILE_BYTES:
        raise ConfigError(too_big)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror or exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(too_big)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"config file {p} is not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start}"
        ) from None


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping with the safe loader; an empty file is an empty mapping.

    Raises:
        ConfigError: a missing file, a directory, a file over :data:`MAX_FILE_BYTES`, bytes that
            are not UTF-8, invalid YAML (duplicate keys included), nesting past
            :data:`MAX_NESTING`, aliases expanding past :data:`MAX_NODES` values, or a document
            that is not a mapping; the message is one line naming the file.
    """
    p = Path(path)
    text = _read_text(p)
    try:
        data = parse_yaml(text)
    except _LimitError as exc:
        raise ConfigError(
            f"config file {p} is refused: {_yaml_problem(exc)}; expected a plain config"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {p} is not valid YAML: {_yaml_problem(exc)}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:
        # a constructor's own error: an int past str()'s digit limit, a timestamp's month 13
        raise ConfigError(
            f"config file {p} holds a value that cannot be read: {short_repr(str(exc), 200)}"
        ) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} holds a {type(data).__name__}; expected a mapping")
    return data

