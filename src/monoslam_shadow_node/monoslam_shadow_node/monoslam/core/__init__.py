"""ROS-free MonoSLAM: the EKF, its initialisation, gating, RANSAC and tracking-noise estimate."""
