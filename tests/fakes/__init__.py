"""What the tests run against instead of the real thing: a UR controller at the protocol level (fake_ur),
franky-sim's Franka (franka_sim), an arm that ROS 2 drives (ros2_arm), an independent rmw_zenoh client
(ros2_client), a Zenoh router (zenoh_router), a hostile client (flood) and a throw-away certificate
authority (certs). Each runs as the tests' peer, often in a process of its own; none is a test."""
