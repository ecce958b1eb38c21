"""ROS-free fiducial detection: dictionaries, detection, pose and covariance, base frame."""
