"""Typed, bounded access to the YAML configuration; unknown or mistyped keys are errors.

The file is untrusted input too: its size is checked before it is read, it must be UTF-8, YAML
aliases are refused (an alias bomb expands to billions of nodes), nesting is bounded, integers
longer than MAX_INT_DIGITS are refused, and every value echoed in an error is escaped and cut.
"""
from __future__ import annotations

import math
import pathlib
from typing import Any, Sequence

import yaml

from tecdard.safejson import finite, is_number, show, show_name

MAX_CONFIG_BYTES = 1 << 20     # a config file is refused unread beyond this
MAX_NESTING = 16               # mappings and lists nested deeper are refused
MAX_INT_DIGITS = 32
MAX_STR_CHARS = 4096           # any string option (paths included); names have their own, lower limits
MAX_LIST_ITEMS = 1000
MAX_ABS_INT = 1 << 53          # an integer option without bounds of its own


class ConfigError(Exception):
    """A configuration problem, with a one-line message naming the key."""


class _StrictLoader(yaml.SafeLoader):
    """yaml.SafeLoader without aliases, with bounded nesting and integer length."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise ConfigError(f"line {event.start_mark.line + 1}: YAML aliases (*{show_name(event.anchor)}) "
                              "are not accepted; write the value out (an alias bomb expands a small file "
                              "into billions of values)")
        self._depth += 1
        try:
            if self._depth > MAX_NESTING:
                raise ConfigError(f"line {self.peek_event().start_mark.line + 1}: nested deeper than "
                                  f"{MAX_NESTING} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_yaml_int(self, node):
        digits = sum(c.isdigit() for c in node.value)
        if digits > MAX_INT_DIGITS:
            raise ConfigError(f"line {node.start_mark.line + 1}: an integer of {digits} digits "
                              f"(at most {MAX_INT_DIGITS})")
        return super().construct_yaml_int(node)


_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)


class _NoAliasDumper(yaml.SafeDumper):
    def ignore_aliases(self, data) -> bool:
        return True


def dump_yaml(data: Any) -> str:
    """YAML text that Config.load accepts: values written out, never as anchors and aliases
    (yaml.safe_dump writes an alias for an object that appears twice)."""
    return yaml.dump(data, Dumper=_NoAliasDumper)


class _Required:
    def __repr__(self) -> str:
        return "<required>"


REQUIRED = _Required()


class Section:
    """One mapping of the config file.

    Components read *all* of their options through the typed getters, in their
    constructor; `Config.check_unused()` then rejects any key nobody read, which
    catches typos the way Klipper does.
    """

    def __init__(self, data: Any, path: str, root: "Config | None" = None):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"{path or 'the file'}: expected a mapping, got {type(data).__name__}")
        self._data = data
        self.path = path
        self._used: set[str] = set()
        self._children: dict[str, Section] = {}
        self._root = root

    # -- raw access ---------------------------------------------------------
    @property
    def data(self) -> dict:
        """The mapping as read (for a digest of the whole config; components use the getters)."""
        return self._data

    def _name(self, key) -> str:
        key = show_name(key)
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self._data

    def error(self, key: str | None, message: str) -> ConfigError:
        """The error to raise for a problem with `key` of this section (None: the section itself), as
        one line naming it: `raise section.error("band_hz", "expected ...")`. A module raises the error
        of the section it was given, and never imports this module to do so (Klipper's config.error)."""
        return ConfigError(f"{self._name(key) if key is not None else self.path or 'the file'}: {message}")

    def _raw(self, key: str, default: Any) -> Any:
        if key in self._data and self._data[key] is not None:
            self._used.add(key)
            return self._data[key]
        self._used.add(key)
        if default is REQUIRED:
            raise ConfigError(f"{self._name(key)}: missing required option")
        return default

    def section(self, key: str) -> "Section":
        """The sub-mapping `key` (empty if absent)."""
        if key not in self._children:
            self._used.add(key)
            self._children[key] = Section(self._data.get(key), self._name(key), self._root)
        return self._children[key]

    # -- typed getters ------------------------------------------------------
    def getfloat(self, key: str, default: Any = REQUIRED, *, minval: float | None = None,
                 maxval: float | None = None, above: float | None = None) -> float:
        raw = self._raw(key, default)
        value = finite(raw)
        if value is None:
            raise ConfigError(f"{self._name(key)}: expected a finite number, got {show(raw)}")
        self._check_bounds(key, value, minval, maxval, above)
        return value

    def getoptfloat(self, key: str, default: float | None = None, **bounds) -> float | None:
        """A number, or None when the key is absent with no default or is explicitly null (disables a feature)."""
        if key in self._data and self._data[key] is None:
            self._used.add(key)
            return None
        if key not in self._data and default is None:
            self._used.add(key)
            return None
        return self.getfloat(key, default, **bounds)

    def getint(self, key: str, default: Any = REQUIRED, *, minval: int | None = None,
               maxval: int | None = None) -> int:
        value = self._raw(key, default)
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{self._name(key)}: expected an integer, got {show(value)}")
        self._check_bounds(key, value, -MAX_ABS_INT if minval is None else minval,
                           MAX_ABS_INT if maxval is None else maxval, None)
        return value

    def getbool(self, key: str, default: Any = REQUIRED) -> bool:
        value = self._raw(key, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self._name(key)}: expected true or false, got {show(value)}")
        return value

    def getstr(self, key: str, default: Any = REQUIRED, *,
               choices: Sequence[str] | None = None, max_len: int = MAX_STR_CHARS) -> str:
        value = self._raw(key, default)
        if not isinstance(value, str):
            raise ConfigError(f"{self._name(key)}: expected a string, got {show(value)}")
        if len(value) > max_len:
            raise ConfigError(f"{self._name(key)}: {len(value)} characters, at most {max_len}")
        if choices is not None and value not in choices:
            raise ConfigError(f"{self._name(key)}: expected one of {', '.join(choices)}; got {show(value)}")
        return value

    def getstrlist(self, key: str, default: Any = REQUIRED, *, max_len: int = MAX_STR_CHARS,
                   max_items: int = 64) -> list[str]:
        value = self._raw(key, default)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{self._name(key)}: expected a list of strings, got {show(value)}")
        if len(value) > max_items:
            raise ConfigError(f"{self._name(key)}: {len(value)} items, at most {max_items}")
        for v in value:
            if len(v) > max_len:
                raise ConfigError(f"{self._name(key)}: an item of {len(v)} characters, at most {max_len}")
        return list(value)

    def getfloats(self, key: str, default: Any = REQUIRED, *, n: int | None = None,
                  minval: float | None = None, maxval: float | None = None) -> list[float]:
        value = self._raw(key, default)
        out = [finite(v) for v in value] if isinstance(value, (list, tuple)) and len(value) <= MAX_LIST_ITEMS else None
        if out is None or any(v is None for v in out):
            raise ConfigError(f"{self._name(key)}: expected a list of finite numbers, got {show(value)}")
        if n is not None and len(value) != n:
            raise ConfigError(f"{self._name(key)}: expected {n} numbers, got {len(value)}")
        for v in out:
            self._check_bounds(key, v, minval, maxval, None)
        return out

    def getrows(self, key: str, default: Any = REQUIRED, *, width: int, max_rows: int = MAX_LIST_ITEMS,
                min_rows: int = 1, what: str = "row") -> list[list[float]]:
        """A list of min_rows to max_rows rows of `width` finite numbers each (a table such as [[grip
        force N, eta], ...]); `what` names a row in the errors."""
        value = self._raw(key, default)
        kind = "pairs" if width == 2 else "rows"
        if not isinstance(value, list) or len(value) < min_rows or len(value) > max_rows:
            raise self.error(key, f"expected a list of up to {max_rows} {what} {kind}")
        out = []
        for row in value:
            if not isinstance(row, list) or len(row) != width or not all(is_number(x) for x in row):
                raise self.error(key, f"expected {what} {kind}, got {show(row)}")
            numbers = [finite(x) for x in row]
            if any(x is None for x in numbers):
                raise self.error(key, f"{show(row)} is not finite")
            out.append(numbers)
        return out

    def getvec3(self, key: str, default: Any = REQUIRED, *, unit: bool = False) -> list[float]:
        vec = self.getfloats(key, default, n=3)
        if unit:
            norm = math.sqrt(sum(v * v for v in vec))
            if norm < 1e-9:
                raise ConfigError(f"{self._name(key)}: expected a non-zero direction, got {vec}")
            vec = [v / norm for v in vec]
        return vec

    def getquat(self, key: str, default: Any = REQUIRED) -> list[float]:
        """Unit quaternion (x, y, z, w); rejected if |q| is off by more than 1e-3."""
        q = self.getfloats(key, default, n=4)
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > 1e-3:
            raise ConfigError(f"{self._name(key)}: quaternion (x, y, z, w) must have unit norm, got |q|={norm:.4f}")
        return [v / norm for v in q]

    def _check_bounds(self, key: str, value: float, minval: Any, maxval: Any, above: Any) -> None:
        if minval is not None and value < minval:
            raise ConfigError(f"{self._name(key)}: {value} is below the minimum {minval}")
        if maxval is not None and value > maxval:
            raise ConfigError(f"{self._name(key)}: {value} is above the maximum {maxval}")
        if above is not None and value <= above:
            raise ConfigError(f"{self._name(key)}: {value} must be greater than {above}")

    # -- unknown keys -------------------------------------------------------
    def unused_keys(self) -> list[str]:
        return [name for name, _ in self._unused()]

    def _unused(self) -> list[tuple[str, str | None]]:
        """(the key no component read, the option of its section it is closest to, or None), section by section:
        the options a section's readers asked for are its known ones (a typo's likely intent)."""
        import difflib
        known = {str(k).lower(): str(k) for k in self._used}
        out = []
        for k in self._data:
            if k not in self._used:
                close = difflib.get_close_matches(str(k).lower(), list(known), n=1, cutoff=0.75)
                out.append((self._name(k), self._name(known[close[0]]) if close else None))
        for child in self._children.values():
            out.extend(child._unused())
        return out


class Config(Section):
    """The root of a configuration file."""

    def __init__(self, data: Any, source: str = "<config>"):
        self.source = source
        super().__init__(data, "", self)

    @classmethod
    def load(cls, path: str | pathlib.Path) -> "Config":
        path = pathlib.Path(path)
        name = show_name(str(path), 200)
        try:
            with open(path, "rb") as fh:
                raw = fh.read(MAX_CONFIG_BYTES + 1)
        except FileNotFoundError:
            raise ConfigError(f"{name}: no such config file") from None
        except IsADirectoryError:
            raise ConfigError(f"{name}: is a directory, not a config file") from None
        except OSError as exc:
            raise ConfigError(f"{name}: cannot read config file ({exc.strerror})") from None
        if len(raw) > MAX_CONFIG_BYTES:
            raise ConfigError(f"{name}: larger than {MAX_CONFIG_BYTES} bytes")
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            hint = " (UTF-16?)" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else ""
            raise ConfigError(f"{name}: not UTF-8 text{hint} (byte {exc.start})") from None
        try:
            data = yaml.load(text, Loader=_StrictLoader)    # noqa: S506 (a SafeLoader, stricter still)
        except ConfigError as exc:
            raise ConfigError(f"{name}: {exc}") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}" if mark is not None else ""
            problem = getattr(exc, "problem", None) or "invalid YAML"
            raise ConfigError(f"{name}:{where}: {show_name(problem, 200)}") from None
        except (ValueError, RecursionError, OverflowError, MemoryError) as exc:
            raise ConfigError(f"{name}: not a valid config ({type(exc).__name__})") from None
        if data is None:
            data = {}
        return cls(data, str(path))

    def check_unused(self) -> None:
        """Raise ConfigError naming the first key that no component read."""
        unused = self._unused()
        if unused:
            name, hint = unused[0]
            raise ConfigError(f"{name}: unknown option" + (f" (did you mean {hint}?)" if hint else ""))
