"""ROS-free EM-SAM core: SE(2) helpers, factors, sparse least squares, EM, evaluation."""
