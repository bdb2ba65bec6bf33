"""The shipped systemd units and udev rule, installed as package data (tecdard.systemd): found by
tecdard.shipped.systemd(name)."""
