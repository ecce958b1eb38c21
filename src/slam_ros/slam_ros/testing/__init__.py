"""Topic-level test harness: isolated DDS domain, nodes in-process or as subprocesses,
publishers and collectors with deadline-based waits, and synthetic messages and bags.

Enable it in a conftest.py with ``pytest_plugins = ['slam_ros.testing.pytest_plugin']``.
"""
