"""Fiducial detection (cv2.aruco) and range-bearing observations in the robot base frame."""
