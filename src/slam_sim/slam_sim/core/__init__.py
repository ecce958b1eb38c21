"""ROS-free simulation cores (numpy, scipy, OpenCV); randomness comes in as
``np.random.Generator``."""
