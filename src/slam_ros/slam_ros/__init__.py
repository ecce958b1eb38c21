"""ROS plumbing for nodes and tools: QoS, main(), parameters, types, bags, test harness."""
