"""ROS-free cores: uncertain projective geometry, the Shadow filter and its classifier."""
