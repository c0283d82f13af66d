"""Marker-space retargeting of an actor's performance onto character rigs.

- :mod:`rigbuild.retarget.common`: marker mapping, stabilization, metrics, weight-curve writers (shared).
- :mod:`rigbuild.retarget.ribera`: range-of-motion alignment + geometric prior (Ribera et al. 2017).
"""
