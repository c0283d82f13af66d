"""Marker-space retargeting of an actor's performance onto character rigs.

- :mod:`rigbuild.retarget.methods`: the methods the pipeline runs and their metric keys (the registry).
- :mod:`rigbuild.retarget.params`: ``params.retarget`` (Ribera and Seol parameters, typed, with their defaults).
- :mod:`rigbuild.retarget.stage`: the jobs of rules ``retarget_ribera`` and ``retarget_seol``.
- :mod:`rigbuild.retarget.common`: marker mapping, stabilization, low-pass filtering (shared).
- :mod:`rigbuild.retarget.ribera` (a package, one module per concept): range-of-motion alignment + geometric
  prior (Ribera et al. 2017); :mod:`rigbuild.retarget.run`: one Ribera retargeting from arrays.
- :mod:`rigbuild.retarget.seol` (a package, one module per concept): spacetime expression cloning (Seol et al.
  2012); editing in :mod:`rigbuild.retarget.editing`.
- :mod:`rigbuild.retarget.plausible`: the antagonist table, shape regions and the plausibility metrics of a
  weight sequence (both methods' plausibility options use them).
"""
