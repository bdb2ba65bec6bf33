"""Typed, bounded access to the YAML configuration; unknown or mistyped keys are errors."""
from __future__ import annotations

import math
import pathlib
from typing import Any, Sequence

import yaml


class ConfigError(Exception):
    """A configuration problem, with a one-line message naming the key."""


class _Required:
    def __repr__(self) -> str:
        return "<required>"


REQUIRED = _Required()


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


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
            raise ConfigError(f"{path}: expected a mapping, got {type(data).__name__}")
        self._data = data
        self.path = path
        self._used: set[str] = set()
        self._children: dict[str, Section] = {}
        self._root = root

    # -- raw access ---------------------------------------------------------
    def _name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self._data

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
        value = self._raw(key, default)
        if not _is_number(value) or not math.isfinite(float(value)):
            raise ConfigError(f"{self._name(key)}: expected a finite number, got {value!r}")
        value = float(value)
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
            raise ConfigError(f"{self._name(key)}: expected an integer, got {value!r}")
        self._check_bounds(key, value, minval, maxval, None)
        return value

    def getbool(self, key: str, default: Any = REQUIRED) -> bool:
        value = self._raw(key, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self._name(key)}: expected true or false, got {value!r}")
        return value

    def getstr(self, key: str, default: Any = REQUIRED, *,
               choices: Sequence[str] | None = None) -> str:
        value = self._raw(key, default)
        if not isinstance(value, str):
            raise ConfigError(f"{self._name(key)}: expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise ConfigError(f"{self._name(key)}: expected one of {', '.join(choices)}; got {value!r}")
        return value

    def getstrlist(self, key: str, default: Any = REQUIRED) -> list[str]:
        value = self._raw(key, default)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{self._name(key)}: expected a list of strings, got {value!r}")
        return list(value)

    def getfloats(self, key: str, default: Any = REQUIRED, *, n: int | None = None,
                  minval: float | None = None, maxval: float | None = None) -> list[float]:
        value = self._raw(key, default)
        if (not isinstance(value, (list, tuple))
                or not all(_is_number(v) and math.isfinite(float(v)) for v in value)):
            raise ConfigError(f"{self._name(key)}: expected a list of numbers, got {value!r}")
        if n is not None and len(value) != n:
            raise ConfigError(f"{self._name(key)}: expected {n} numbers, got {len(value)}")
        out = [float(v) for v in value]
        for v in out:
            self._check_bounds(key, v, minval, maxval, None)
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
        out = [self._name(k) for k in self._data if k not in self._used]
        for child in self._children.values():
            out.extend(child.unused_keys())
        return out


class Config(Section):
    """The root of a configuration file."""

    def __init__(self, data: Any, source: str = "<config>"):
        self.source = source
        super().__init__(data, "", self)

    @classmethod
    def load(cls, path: str | pathlib.Path) -> "Config":
        path = pathlib.Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such config file") from None
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read config file ({exc.strerror})") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}" if mark is not None else ""
            problem = getattr(exc, "problem", None) or "invalid YAML"
            raise ConfigError(f"{path}:{where}: {problem}") from None
        if data is None:
            data = {}
        return cls(data, str(path))

    def check_unused(self) -> None:
        """Raise ConfigError naming the first key that no component read."""
        unused = self.unused_keys()
        if unused:
            raise ConfigError(f"{unused[0]}: unknown option")
