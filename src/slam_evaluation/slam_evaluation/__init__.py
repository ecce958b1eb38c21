"""Top floor of the suite: every evaluator, metric, report and plot of both papers.

It composes the node packages' processors with the simulators in ``slam_sim``; nothing
below imports it.
"""
