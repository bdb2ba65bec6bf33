"""The `tecdard` command line and the Zenoh client it, the demo and the tests use."""
