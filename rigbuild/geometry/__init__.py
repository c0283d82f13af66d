"""Geometry shared by the stages: rigid and similarity fits, mesh operators."""

from rigbuild.geometry.rigid import apply_rigid, fit_rigid_motion, fit_similarity, rotation_angle_deg

__all__ = ["apply_rigid", "fit_rigid_motion", "fit_similarity", "rotation_angle_deg"]
