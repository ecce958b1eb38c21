"""ROS-free feature tracking: detection, KLT tracking and re-identification."""
