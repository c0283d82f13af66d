"""Multi-camera rig calibration from ChArUco / chessboard images (issue 3).

detect (corners) -> intrinsics (per camera) -> posegraph (initial extrinsics) -> bundle (global robust BA)
-> qa (gates); :mod:`rigbuild.calibrate.rig` runs the chain, :mod:`rigbuild.calibrate.session` runs it on a
session folder and writes the outputs; :mod:`rigbuild.calibrate.stage` is rule ``calibrate``'s runner and
:mod:`rigbuild.calibrate.params` the stage's parameters.
"""
