"""ROS-free pieces the cores share: projective geometry, tracking noise, pose links, inputs."""
