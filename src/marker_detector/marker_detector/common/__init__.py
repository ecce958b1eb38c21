"""What the two nodes share: the sightings and camera_info message layer."""
