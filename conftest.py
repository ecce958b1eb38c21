"""Workspace-wide pytest configuration: the topic-level test harness."""

pytest_plugins = ['slam_ros.testing.pytest_plugin']
