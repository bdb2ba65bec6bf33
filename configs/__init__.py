"""The shipped configs, installed as package data (tecdard.configs): tecdard.shipped.config(name) finds them."""
