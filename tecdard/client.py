"""The daemon's Zenoh client, for a planner's or a tool's own process: `from tecdard.client import Client`.

It imports Zenoh and the API's keys and payload rules, never the estimator, Pinocchio or numba, so
that a process that only sends tasks and watches state stays light (`pip install tecdar` and this)."""
from tecdard.api.client import Client, ClientError

__all__ = ["Client", "ClientError"]
