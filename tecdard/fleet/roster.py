"""The fleet's roster: who is who on the router mesh, read from YAML and checked. Names are certificates'
common names: a robot's daemon holds a certificate named after its robot, an operator's client one named
after the operator, each router one of its own (docs/fleet.md, "Roster and ACL")."""
from __future__ import annotations

import pathlib
from dataclasses import dataclass

from tecdard.config import Config, ConfigError
from tecdard.safejson import show

MAX_NAME_CHARS = 64           # a robot's name is a chunk of every key expression (as robot.name)
MAX_MEMBERS = 1024            # robots, operators or routers in one roster
ALL_ROBOTS = "*"              # in an operator's list: every robot of the roster


def name_problem(name) -> str | None:
    """Why `name` cannot be a robot's, an operator's or a router's name, or None: ASCII letters,
    digits, '-', '_' (and '.' for people and routers), at most MAX_NAME_CHARS; a robot's also a chunk
    of its key expressions (robot.name's rule)."""
    if not isinstance(name, str) or not name:
        return "an empty or non-string name"
    if len(name) > MAX_NAME_CHARS:
        return f"a name of {len(name)} characters, at most {MAX_NAME_CHARS}"
    if not name.isascii() or not name.replace("_", "").replace("-", "").replace(".", "").isalnum():
        return f"{show(name)}: letters, digits, '-', '_' or '.' only"
    return None


@dataclass(frozen=True)
class Roster:
    """robots: their names; operators: name -> the robots it may command; routers: the routers'
    certificates' names (the routers trust each other with everything under tecdar/)."""
    robots: tuple[str, ...]
    operators: dict
    routers: tuple[str, ...]

    @classmethod
    def load(cls, path: str | pathlib.Path) -> "Roster":
        """The roster file (ConfigError: one line naming the file, the key and what is wrong)."""
        cfg = Config.load(path)
        roster = cls.from_config(cfg)
        cfg.check_unused()
        return roster

    @classmethod
    def from_config(cls, cfg) -> "Roster":
        robots = _names(cfg, "robots", cfg.getstrlist("robots", max_len=MAX_NAME_CHARS, max_items=MAX_MEMBERS))
        if not robots:
            raise cfg.error("robots", "an empty list: a roster names at least one robot")
        for robot in robots:
            if "." in robot:
                raise cfg.error("robots", f"{show(robot)}: a robot's name is letters, digits, '-' or '_' "
                                          "(it is a chunk of its key expressions)")
        routers = _names(cfg, "routers", cfg.getstrlist("routers", [], max_len=MAX_NAME_CHARS, max_items=MAX_MEMBERS))
        section = cfg.section("operators") if cfg.has("operators") else None
        operators = {}
        for name in (section.data if section is not None else {}):
            problem = name_problem(name)
            if problem:
                raise section.error(str(name)[:MAX_NAME_CHARS], problem)
            may = section.getstrlist(name, max_len=MAX_NAME_CHARS, max_items=MAX_MEMBERS)
            if ALL_ROBOTS in may:
                may = list(robots)
            unknown = [r for r in may if r not in robots]
            if unknown:
                raise section.error(name, f"{show(unknown[0])} is not a robot of the roster "
                                          f"(robots: {', '.join(robots)})")
            operators[name] = tuple(dict.fromkeys(may))
        taken = {}
        for kind, names in (("robot", robots), ("router", routers), ("operator", list(operators))):
            for name in names:
                if name in taken:
                    raise cfg.error(kind + "s", f"{show(name)} is both a {taken[name]} and a {kind}: each "
                                                "certificate name has one role")
                taken[name] = kind
        return cls(tuple(robots), operators, tuple(routers))


def _names(cfg, key: str, names: list[str]) -> list[str]:
    for name in names:
        problem = name_problem(name)
        if problem:
            raise cfg.error(key, problem)
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise cfg.error(key, f"{show(dup)} is listed twice")
    return names


__all__ = ["ALL_ROBOTS", "ConfigError", "Roster", "name_problem"]
