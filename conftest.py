"""Workspace-wide pytest configuration: the topic-level test harness."""

pytest_plugins = ['slam_bringup.testing.pytest_plugin']
