"""ROS-free pieces the three cores share: uncertain projective geometry, tracking noise,
pose links, the input types and the feature status codes."""
