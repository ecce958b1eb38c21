"""Topic-level test harness: isolated DDS domain, nodes, probes, synthetic messages, bags.

Enable it in a conftest.py with ``pytest_plugins = ['slam_ros.testing.pytest_plugin']``."""
