"""The shipped systemd units and udev rule, installed as package data (tecdard.systemd): tecdard.shipped.systemd(name)."""
