"""What the project ships beside its code, found where it is installed, never by walking up from a source file:
the configs (`tecdard.configs`: sim.yaml, ur5e.yaml, fr3.yaml, router.yaml, roster.yaml), the systemd units
and the board's udev rule (`tecdard.systemd`), and the firmware's host board (the simulator's sim-firmware
source). A wheel carries them as package data (pyproject's package-dir maps the checkout's configs/ and
systemd/ under tecdard, as it maps drivers/ and the rest; setup.py builds the host board into it); an
editable install finds the same packages in the checkout.
"""
from __future__ import annotations

import importlib.util
import pathlib

HOST_BOARD_NAME = "host-board"


def _package_dir(name: str) -> pathlib.Path:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"{name}: not installed (reinstall tecdar)")
    return pathlib.Path(next(iter(spec.submodule_search_locations)))


def config(name: str) -> pathlib.Path:
    """A shipped config file by name (sim.yaml, ur5e.yaml, fr3.yaml, router.yaml, roster.yaml)."""
    return _package_dir("tecdard.configs") / name


def systemd(name: str) -> pathlib.Path:
    """A shipped systemd unit or udev rule by name (tecdard.service, 99-tecdar-imu.rules, ...)."""
    return _package_dir("tecdard.systemd") / name


def host_board() -> pathlib.Path:
    """The firmware's host board: the one a wheel carries (tecdard/firmware/host-board), else, from a
    checkout, the one `make firmware` builds (firmware/build/host-board, beside the checkout's configs/).
    sim.host_board names another."""
    wheel = _package_dir("tecdard") / "firmware" / HOST_BOARD_NAME
    if wheel.exists():
        return wheel
    checkout = _package_dir("tecdard.configs").parent
    built = checkout / "firmware" / "build" / HOST_BOARD_NAME
    return built if (checkout / "firmware" / "Makefile").exists() else wheel
