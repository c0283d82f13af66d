"""Errors against ground truth (synthetic sessions) and the names of those metrics.

Run only by the evaluation rules (rules/eval.smk) and tests; no stage job imports this package, and only it
and tests read a session's ``ground_truth/``.
"""
