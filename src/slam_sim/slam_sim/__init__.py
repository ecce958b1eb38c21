"""Seeded simulated worlds with ground truth, written as rosbag2 bags."""
