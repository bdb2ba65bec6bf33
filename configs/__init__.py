"""The shipped configs, installed as package data (tecdard.configs): found by tecdard.shipped.config(name)."""
