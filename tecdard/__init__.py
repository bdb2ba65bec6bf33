"""tecdard: the daemon, its threads, configuration, Zenoh interface and command line."""
__version__ = "0.1.0"
