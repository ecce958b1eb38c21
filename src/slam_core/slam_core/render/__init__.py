"""The suite's renderer of textured planar patches (printed markers on paper), ROS-free:
textures and texture sampling (``texture``), the per-pixel rays of a camera (``rays``) and
ray-patch intersection and compositing (``patch``). The simulators' office and dynamic
cameras and marker_detector's synthetic test images all draw their markers with it."""
