"""One-line error messages of the configuration: :class:`ConfigError`, values cut short in
bounded time (:func:`short_repr`) and pydantic validation errors as one line naming each field,
its value and what was expected (:func:`_format_errors`)."""

from __future__ import annotations

import math
import reprlib
from typing import Any

from pydantic import ValidationError


class ConfigError(ValueError):
    """A configuration file or override that does not validate; the message names every field."""


#: Longest shown value or key in an error message [characters].
MAX_SHOWN = 80
#: Errors listed in one message; the rest are counted.
MAX_LISTED = 5

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxdict, _REPR.maxlist, _REPR.maxtuple, _REPR.maxset = 3, 4, 4, 4, 4
_REPR.maxstring, _REPR.maxlong, _REPR.maxother = MAX_SHOWN, 40, MAX_SHOWN


def short_repr(value: Any, limit: int = MAX_SHOWN) -> str:
    """``repr`` of a value cut to ``limit`` characters, in bounded time whatever its size.

    A billion-laughs structure, a huge int or a hostile ``__repr__`` never reaches ``repr``
    whole; the result is one line.
    """
    if isinstance(value, int) and value.bit_length() > 128:
        return f"<int of {int(value.bit_length() * math.log10(2)) + 1} digits>"
    try:
        text = _REPR.repr(value)
    except Exception:  # noqa: BLE001  (an int past str()'s digit limit, a failing __repr__)
        text = f"<{type(value).__name__}>"
    text = text.replace("\n", "\\n")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _expected(msg: str) -> str:
    for prefix in ("Input should be ", "Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
            break
    msg = " ".join(msg.split())
    return (msg[:1].lower() + msg[1:])[:200]


def _loc(loc: tuple[Any, ...]) -> str:
    return ".".join(p if isinstance(p, str) and p.isprintable() and len(p) <= 40 else short_repr(p, 40)
                    for p in loc) or "<root>"


def _format_errors(exc: ValidationError, source: str) -> str:
    """One line: each error's field, its value (cut short) and what was expected."""
    errors = exc.errors()
    items = []
    for err in errors[:MAX_LISTED]:
        loc, value = _loc(err["loc"]), short_repr(err.get("input"))
        if err["type"] == "extra_forbidden":
            items.append(f"{loc}: unknown key (value {value}); check the spelling")
        elif err["type"] == "missing":
            items.append(f"{loc}: missing; expected a value (the field is required)")
        else:
            items.append(f"{loc}: got {value}, expected {_expected(err['msg'])}")
    if len(errors) > MAX_LISTED:
        items.append(f"and {len(errors) - MAX_LISTED} more")
    return f"invalid configuration in {source}: " + "; ".join(items)

