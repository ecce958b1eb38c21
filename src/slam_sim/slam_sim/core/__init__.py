"""ROS-free simulation cores; randomness comes in as ``np.random.Generator``."""
