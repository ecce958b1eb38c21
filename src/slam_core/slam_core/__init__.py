"""ROS-free ground floor: errors, stamps, files, progress, geometry, camera, parameters."""
