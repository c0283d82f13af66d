"""Synthetic capture sessions with known ground truth (rigs, actors, motion, cameras, images)."""
