"""Evaluation against ground truth and campaigns: the thesis's tables, pose-error sensitivity, landings.

May import every other package; no other package imports it.
"""
