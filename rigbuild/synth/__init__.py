"""The test-data generator: synthetic capture sessions with known ground truth (actors, motion, cameras, images).

Built on the production assets in :mod:`rigbuild.assets` (the procedural head, the marker sets); only the
generator rules, ground-truth evaluation, tests and benchmarks import this package.
"""
