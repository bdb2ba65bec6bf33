"""The task verbs: one module per verb in this package, each defining `VERB`, a `TaskVerb`.

A verb's module says everything the daemon and the CLI need of it: its payload fields with their
types, defaults and limits (tecdard.commands validates any payload against them, and the CLI makes
its options from them), and how the task is built from validated fields. Adding a verb is adding a
module here (and its test); nothing else names the verbs. `discover()` imports every module of the
package's path once, in name order.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from tecdard.control.plugins import new_modules

REQUIRED = object()          # a Field's default: the field must be given


@dataclass(frozen=True)
class Field:
    """One payload field. `default`, `lo` and `hi` are values or callables of the configured
    `tecdard.commands.Limits` (the limits come from the config)."""
    name: str
    kind: str                  # number | direction | numbers | choice | bool | grid | int_choice
    default: object = REQUIRED
    lo: object = None
    hi: object = None
    unit: str = ""
    help: str = ""
    n: int = 3                 # numbers: how many
    choices: tuple = ()        # choice, int_choice: the allowed values

    def resolve(self, attr: str, limits):
        value = getattr(self, attr)
        return value(limits) if callable(value) else value

    @property
    def option(self) -> str:
        """The CLI option: --angle-deg for angle_deg."""
        return "--" + self.name.replace("_", "-")


class BuildRefused(ValueError):
    """A task that validated fields cannot make here (a map leaving the workspace box): the
    command is refused as out_of_limits with this message."""


@dataclass(frozen=True)
class TaskContext:
    """What a verb's `build` may know when the control thread starts its task."""
    task_id: str
    p_tcp: np.ndarray                  # the measured TCP position, world, m
    R_hold: np.ndarray                 # the orientation the arm holds, world <- TCP
    max_speed_m_s: float               # the configured TCP speed limit
    workspace_min: tuple               # the workspace box, world, m
    workspace_max: tuple
    map_settings: object = None        # tecdard.mapfiles.MapSettings
    write_map: Callable | None = None  # hands a MapRecord to the map-writer thread, returns a Future


@dataclass(frozen=True)
class TaskVerb:
    name: str
    summary: str                                   # one line, for the CLI's help
    fields: tuple                                  # Field, in validation order
    build: Callable                                # (fields: dict, ctx: TaskContext) -> control.tasks.Task
    self_check: dict = field(default_factory=dict)  # the required fields' values: Limits checks every default


REGISTRY: dict[str, TaskVerb] = {}
_discovered: set[str] = set()


def register(verb: TaskVerb) -> TaskVerb:
    if verb.name in REGISTRY and REGISTRY[verb.name] is not verb:
        raise ValueError(f"task verb {verb.name!r} is defined twice")
    REGISTRY[verb.name] = verb
    return verb


def discover() -> dict[str, TaskVerb]:
    """Import every verb module on this package's path (once each) and register its VERB."""
    for module in new_modules(__path__, __name__, _discovered):
        verb = getattr(module, "VERB", None)
        if not isinstance(verb, TaskVerb):
            raise TypeError(f"{module.__name__}: a verb module defines VERB = TaskVerb(...)")
        register(verb)
    return REGISTRY


def names() -> tuple[str, ...]:
    """The task verbs, in registration order."""
    return tuple(discover())


def get(name: str) -> TaskVerb | None:
    return discover().get(name)
