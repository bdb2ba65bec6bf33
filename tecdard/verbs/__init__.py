"""The task verbs: one module (or package) per verb in this package, each defining `VERB`, a `TaskVerb`.

A verb's module says everything the daemon and the CLI need of it: its payload fields with their
types, defaults and limits (tecdard.api.commands validates any payload against them, and the CLI
makes its options from them), how the task is built from validated fields, and, where its tasks need
one, its `service`: its long-lived part beside the control thread, built once from its own config
section (the map's file writer). Adding a verb is adding a module here (and its test); nothing else
names the verbs. `discover()` imports every module of the package's path once, in name order.
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


class VerbService:
    """A verb's long-lived part beside the control thread: what its tasks hand work to off the 20 ms
    tick (the map's fusing and file writing), built once from the verb's config section. The control
    thread asks it for its events every tick, waits for it to be idle before an orderly shutdown, and
    shuts it down when it ends."""

    def announcements(self) -> list[dict]:
        """Event fields (kind first) of whatever it finished since the last call."""
        return []

    @property
    def idle(self) -> bool:
        """Nothing of its work is still under way."""
        return True

    def shutdown(self) -> None:
        """Stop taking work (the daemon is ending)."""


@dataclass(frozen=True)
class TaskContext:
    """What a verb's `build` may know when the control thread starts its task."""
    task_id: str
    p_tcp: np.ndarray                  # the measured TCP position, world, m
    R_hold: np.ndarray                 # the orientation the arm holds, world <- TCP
    max_speed_m_s: float               # the configured TCP speed limit
    workspace_min: tuple               # the workspace box, world, m
    workspace_max: tuple
    service: VerbService | None = None   # the verb's own service (TaskVerb.service), if it has one
    q: np.ndarray | None = None          # the measured joints, rad
    q_home: np.ndarray | None = None     # robot.q_home, rad
    fk: Callable | None = None           # q -> the TCP position, world, m
    world: object | None = None          # the simulator's world control (let go, rebuild); None on a real arm


@dataclass(frozen=True)
class TaskVerb:
    name: str
    summary: str                                   # one line, for the CLI's help
    fields: tuple                                  # Field, in validation order
    build: Callable                                # (fields: dict, ctx: TaskContext) -> control.tasks.Task
    self_check: dict = field(default_factory=dict)  # the required fields' values: Limits checks every default
    service: Callable | None = None                # (its config section, named as the verb) -> VerbService
    example: str = ""                              # one command line, for the CLI's help


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


def services(cfg) -> dict[str, VerbService]:
    """Every verb's service, each built from the config section named as its verb (`map`)."""
    return {verb.name: verb.service(cfg.section(verb.name)) for verb in discover().values()
            if verb.service is not None}
