"""Evaluation against ground truth (synthetic sessions); only rigbuild.eval and tests read ground_truth/."""
