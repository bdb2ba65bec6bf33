"""Bounded JSON for untrusted text: nesting depth, number length and finiteness are checked, and
values are shown back to the sender escaped and truncated."""
from __future__ import annotations

import json
import math

import numpy as np

MAX_DEPTH = 32                # arrays and objects nested deeper are refused before parsing
MAX_NUMBER_CHARS = 32         # a float64 needs at most 24 characters ("-2.2250738585072014e-308")
SHOW_CHARS = 64               # a value or name echoed in an error message is cut to this many characters

_QUOTE, _BACKSLASH = ord('"'), ord("\\")
_LBRACKET, _LBRACE, _RBRACKET, _RBRACE = b"[{]}"


class JsonLimitError(ValueError):
    """Text that is not JSON or exceeds a limit; the message is one line."""


def nesting_depth(text: str) -> int:
    """The deepest nesting of [ and { in JSON text, outside strings: linear numpy passes, no
    recursion and no backtracking whatever the text (a quote preceded by an odd run of
    backslashes is escaped)."""
    b = np.frombuffer(text.encode("utf-8", "surrogatepass"), np.uint8)
    idx = np.arange(b.size)
    last_plain = np.maximum.accumulate(np.where(b != _BACKSLASH, idx, -1))   # last non-backslash at or before i
    quotes = np.flatnonzero(b == _QUOTE)
    run = quotes - 1 - np.where(quotes > 0, last_plain[np.maximum(quotes - 1, 0)], -1)
    real = quotes[run % 2 == 0]                       # the quotes that open or close a string
    opening, closing = (b == _LBRACKET) | (b == _LBRACE), (b == _RBRACKET) | (b == _RBRACE)
    brackets = np.flatnonzero(opening | closing)
    outside = np.searchsorted(real, brackets) % 2 == 0
    step = np.where(opening[brackets], 1, -1)[outside]
    return int(np.cumsum(step).max(initial=0))


def _parse_int(s: str) -> int:
    if len(s) > MAX_NUMBER_CHARS:
        raise JsonLimitError(f"an integer of {len(s)} characters (at most {MAX_NUMBER_CHARS})")
    return int(s)


def _parse_float(s: str) -> float:
    if len(s) > MAX_NUMBER_CHARS:
        raise JsonLimitError(f"a number of {len(s)} characters (at most {MAX_NUMBER_CHARS})")
    v = float(s)
    if v in (float("inf"), float("-inf")):
        raise JsonLimitError(f"the number {s} is out of the float64 range")
    return v


def _parse_constant(s: str):
    raise JsonLimitError(f"{s} is not a JSON number")


def loads(text: str, max_depth: int = MAX_DEPTH):
    """json.loads with limits; JsonLimitError (one line) for malformed JSON, nesting deeper than
    max_depth, numbers longer than MAX_NUMBER_CHARS, and NaN, Infinity or out-of-range numbers."""
    if text.count("[") + text.count("{") > max_depth:      # else it cannot nest deeper: no need to look
        depth = nesting_depth(text)
        if depth > max_depth:
            raise JsonLimitError(f"nested {depth} levels deep (at most {max_depth})")
    try:
        return json.loads(text, parse_int=_parse_int, parse_float=_parse_float, parse_constant=_parse_constant)
    except JsonLimitError:
        raise
    except json.JSONDecodeError as exc:
        raise JsonLimitError(f"malformed JSON ({exc.msg} at char {exc.pos})") from None
    except RecursionError:      # unreachable below MAX_DEPTH; kept so that no input can raise it
        raise JsonLimitError("nested too deeply") from None


def is_number(v) -> bool:
    """An int or float, not a bool (JSON and YAML both give booleans that Python counts as ints)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def finite(v) -> float | None:
    """v as a finite float, or None: not a number, a bool, beyond the float range, NaN or inf."""
    if not is_number(v):
        return None
    try:
        f = float(v)
    except (OverflowError, ValueError):
        return None
    return f if math.isfinite(f) else None


def show(value, limit: int = SHOW_CHARS) -> str:
    """A value as one line of escaped JSON (names as quoted strings), cut to `limit` characters."""
    try:
        text = json.dumps(value, ensure_ascii=True, separators=(",", ":"), allow_nan=True)
    except (TypeError, ValueError, RecursionError):
        text = ascii(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def first_line(exc: BaseException, limit: int = 300) -> str:
    """An exception's message as one line for a person: its first non-blank line (its type's name
    when it has none), without a Rust library's source location (Zenoh's and obstore's errors end
    `at /root/.cargo/...`), cut to `limit` characters."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text.split(" at /root/.cargo")[0].split(" at /home/")[0][:limit]


def show_name(name: str, limit: int = SHOW_CHARS) -> str:
    """A field name or verb as it can be echoed: escaped (no control characters, ASCII), cut to `limit`."""
    text = json.dumps(str(name), ensure_ascii=True)[1:-1]
    return text if len(text) <= limit else text[:limit - 3] + "..."


def json_ready(x):
    """A value JSON can carry as it is: numpy values as Python ones, NaN and infinities as null (JSON
    has no such numbers, and strict parsers refuse them), anything else as its text."""
    if isinstance(x, dict):
        return {str(k): json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [json_ready(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer, np.bool_)):
        return x.item()
    return x if x is None or isinstance(x, (str, int, bool)) else str(x)


def nonfinite_path(x, path: str = "") -> str | None:
    """Where the first NaN or infinity in a value is ("tcp.p[2]"), or None."""
    if isinstance(x, dict):
        items = ((f"{path}.{k}" if path else str(k), v) for k, v in x.items())
    elif isinstance(x, (list, tuple, np.ndarray)):
        items = ((f"{path}[{i}]", v) for i, v in enumerate(x))
    else:
        return path or "(the value)" if isinstance(x, (float, np.floating)) and not np.isfinite(x) else None
    for sub, v in items:
        found = nonfinite_path(v, sub)
        if found is not None:
            return found
    return None
