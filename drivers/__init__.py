"""Fingertip IMU sources: bytes or simulated physics to timestamped SI samples."""
