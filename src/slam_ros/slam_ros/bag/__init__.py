"""Reading and writing bags with rosbags: ROS 2 (mcap, sqlite3) and ROS 1 (.bag)."""
