"""Evaluators, metrics, reports and plots of both papers; nothing below imports it."""
