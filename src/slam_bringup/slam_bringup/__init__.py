"""Bring-up of the dynamic-SLAM suite: bag tools, graph runner, launch helpers, test harness."""
