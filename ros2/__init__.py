"""tecdard as a ROS 2 node over rmw_zenoh (interface `tecdar-ros2/1`): the tecdar_msgs ament package, the
type support (rosbags), rmw_zenoh's wire conventions, the message conversions and the node."""
