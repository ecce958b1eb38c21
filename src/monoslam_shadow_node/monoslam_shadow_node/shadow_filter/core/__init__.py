"""ROS-free Shadow filter: Pluecker-line rays, the static fit and the chi-square classifier."""
