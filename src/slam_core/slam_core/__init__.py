"""Ground floor of the suite, ROS-free: errors, stamps, console plumbing, report files,
progress, geometry, camera models and the parameter-declaration mechanism."""
