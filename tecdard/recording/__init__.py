"""tecdar-recording/1, which the daemon writes and the tools read, and its form in Foxglove."""
