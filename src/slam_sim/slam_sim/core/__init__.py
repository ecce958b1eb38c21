"""ROS-free simulation cores: numpy only; randomness comes in as ``np.random.Generator``."""
