"""The Zenoh API that the daemon and its clients both speak: keys and sessions, and command payloads checked."""
