"""Pure logic: onset detection, gyro conditioning, contact estimators, planners and task state machines."""
