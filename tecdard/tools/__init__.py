"""The offline tools: localize, calibrate-eta, plot, export, sim-record, imu, doctor, warm and the demo."""
