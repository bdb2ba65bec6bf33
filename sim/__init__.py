"""The simulator: a simulated arm (sim.robot), its world (sim.world), the fingertip's IMU signal (sim.imu)
and board (sim.board), all in a child process (sim.process), plus recorded scenarios (sim.scenarios).

Production code never imports this package: the daemon reaches it only through the robot-backend
registry (robots.backends) when `robot.backend: sim`, and tests, benchmarks, the demo and
`tecdard sim-record` use it directly.
"""
