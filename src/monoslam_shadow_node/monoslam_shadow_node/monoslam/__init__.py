"""The monoslam node: monocular EKF SLAM on the static features."""
