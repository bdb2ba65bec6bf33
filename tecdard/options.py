"""Options declared once: a dataclass field that carries its config key, default, limits, unit and help.

    @dataclass
    class ControlParams:
        tick_s: float = option(0.02, "the control loop's period", unit="s", minval=0.002, maxval=0.1)

    params = read_options(ControlParams, section)        # every declared option, typed and bounded

The config reader (read_options, through the section's typed getters, so that an error names the key as
every other config error does), the docs' table of options (docs/options.md) and `tecdard options`
(with `tecdard run --help`) are generated from the same declaration. A module below tecdard imports this
module, never tecdard.config: it is handed its section and raises that section's errors.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

OPTION = "tecdar.option"          # the key of a field's metadata that holds its Opt


@dataclass(frozen=True)
class Opt:
    """What a config option is, beside its field's default."""
    help: str
    unit: str = ""                # SI, as the key's suffix says it (s, m, N, Hz, deg, ...)
    minval: float | None = None
    maxval: float | None = None
    above: float | None = None    # the value must be greater than this
    choices: tuple[str, ...] | None = None
    kind: str | None = None       # float, int, bool, str, floats, strs, quat, vec3, unitvec3, optfloat, optint,
                                  # optstr ("" is none), optunitvec3, custom (its class reads it itself;
                                  # read_options leaves it); None: the default's
    key: str | None = None        # the config key where it is not the field's name
    max_len: int | None = None    # a string's, or each string's of a list
    max_items: int | None = None  # a list of strings'
    shown: str | None = None      # the default as the docs say it, where it is computed (a directory)
    required: bool = False        # no default: the config must give it


def option(default: Any, help: str, **opt) -> Any:
    """A dataclass field that is a config option (Opt's keywords). A list default is copied for every
    instance; a callable default is called for each (a directory found at run time: give `shown`)."""
    meta = {OPTION: Opt(help, **opt)}
    if callable(default):
        return dataclasses.field(default_factory=default, metadata=meta)
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def declared(cls) -> list[tuple[dataclasses.Field, Opt]]:
    """The fields of the dataclass `cls` that are config options, in their order."""
    return [(f, f.metadata[OPTION]) for f in dataclasses.fields(cls) if OPTION in f.metadata]


def kind_of(f: dataclasses.Field, opt: Opt, default: Any) -> str:
    """The option's kind: its own, else what its default (default_of(f)) says."""
    if opt.kind is not None:
        return opt.kind
    if isinstance(default, bool):
        return "bool"
    if isinstance(default, int):
        return "int"
    if isinstance(default, float):
        return "float"
    if isinstance(default, str):
        return "str"
    if isinstance(default, (list, tuple)):
        return "strs" if default and isinstance(default[0], str) else "floats"
    raise TypeError(f"{f.name}: give the option's kind (its default {default!r} does not say it)")


def default_of(f: dataclasses.Field) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()   # type: ignore[misc]


def _get(section, f: dataclasses.Field, opt: Opt, kind: str, default: Any) -> Any:
    key = opt.key or f.name
    if opt.required:
        if not section.has(key):
            raise section.error(key, "missing required option")
        default = None if kind in ("vec3", "unitvec3", "floats") else default
    bounds = {k: v for k, v in (("minval", opt.minval), ("maxval", opt.maxval)) if v is not None}
    if kind == "float":
        return section.getfloat(key, default, above=opt.above, **bounds)
    if kind == "optfloat":
        return section.getoptfloat(key, default, above=opt.above, **bounds)
    if kind == "int":
        return section.getint(key, default, **bounds)
    if kind == "optint":
        return section.getint(key, 0, **bounds) if section.has(key) else default
    if kind == "optstr":
        return section.getstr(key, "", **({"max_len": opt.max_len} if opt.max_len is not None else {})) or default
    if kind == "bool":
        return section.getbool(key, default)
    if kind == "str":
        return section.getstr(key, default, choices=opt.choices,
                              **({"max_len": opt.max_len} if opt.max_len is not None else {}))
    if kind == "strs":
        return section.getstrlist(key, list(default), **{k: v for k, v in (("max_len", opt.max_len),
                                                                            ("max_items", opt.max_items)) if v})
    if kind == "floats":
        value = section.getfloats(key, list(default), n=len(default), **bounds)
        return tuple(value) if isinstance(default, tuple) else value
    if kind == "optunitvec3":
        return section.getvec3(key, None, unit=True) if section.has(key) else default
    if kind in ("vec3", "unitvec3"):
        value = section.getvec3(key, None if default is None else list(default), unit=kind == "unitvec3")
        return tuple(value) if isinstance(default, tuple) else value
    if kind == "quat":
        return tuple(section.getquat(key, list(default)))
    raise TypeError(f"{f.name}: unknown option kind {kind!r}")


def read_options(cls, section, defaults: dict | None = None, **given):
    """An instance of the dataclass `cls` with every declared option read from `section` (the typed
    getters, with the option's bounds; an error names the key). `defaults`: a field's default where the
    caller knows a better one (a mount from elsewhere in the config); `given`: fields the caller sets,
    not read. Fields that are no option, and options of kind custom (their class reads them), keep
    their defaults unless given."""
    values = {}
    for f, opt in declared(cls):
        if f.name in given or opt.kind == "custom":
            continue
        default = (defaults or {}).get(f.name) if f.name in (defaults or {}) else default_of(f)
        values[f.name] = _get(section, f, opt, kind_of(f, opt, default), default)
    return cls(**values, **given)


def _number(x: float) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, float) and (math.isinf(x) or math.isnan(x)):
        return str(x)
    return f"{x:g}" if isinstance(x, float) else str(x)


def shown_default(f: dataclasses.Field, opt: Opt) -> str:
    if opt.shown is not None:
        return opt.shown
    if opt.required:
        return "required"
    default = default_of(f)
    if default is None:
        return "none"
    if isinstance(default, (list, tuple)):
        return "[" + ", ".join(_number(x) if not isinstance(x, str) else x for x in default) + "]"
    if isinstance(default, str):
        return f'"{default}"' if default else '""'
    return _number(default)


def shown_limits(opt: Opt) -> str:
    parts = []
    if opt.above is not None:
        parts.append(f"> {_number(opt.above)}")
    if opt.minval is not None:
        parts.append(f">= {_number(opt.minval)}")
    if opt.maxval is not None:
        parts.append(f"<= {_number(opt.maxval)}")
    if opt.choices:
        parts.append("one of " + ", ".join(opt.choices))
    return ", ".join(parts)


def rows(path: str, cls) -> list[tuple[str, str, str, str, str]]:
    """(key, default, unit, limits, help) of each option of `cls` read from the section at `path`."""
    return [(f"{path}.{opt.key or f.name}", shown_default(f, opt), opt.unit, shown_limits(opt), opt.help)
            for f, opt in declared(cls)]


def cells(row) -> str:
    """A row of (key, default, unit, limits, help) as a markdown table row, its pipes escaped."""
    key, *rest = (str(c).replace("|", "\\|") for c in row)
    return "| `" + key + "` | " + " | ".join(rest) + " |"


def text(sections, only: str | None = None) -> str:
    """The options of (path, options class) pairs for a terminal: `key = default unit (limits): help`, a
    line each; `only` a section path (and those under it). docs/options.md's tables: tecdard.cli.options."""
    out = []
    for path, cls in sections:
        if only is not None and path != only and not path.startswith(only + "."):
            continue
        for k, d, u, lim, h in rows(path, cls):
            unit = f" {u}" if u else ""
            limits = f" ({lim})" if lim else ""
            out.append(f"{k} = {d}{unit}{limits}: {h}")
    return "\n".join(out)
