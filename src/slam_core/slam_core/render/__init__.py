"""The suite's ROS-free renderer of textured planar patches (printed markers)."""
