"""ROS plumbing shared by every node and offline tool: QoS, the Jazzy main(), parameter
declaration on rclpy nodes, message types, bag reading and writing with rosbags, and the
topic-level test harness."""
