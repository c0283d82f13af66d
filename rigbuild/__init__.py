"""rigbuild: multi-camera facial capture -> personalized blendshape rig -> retargeted animation.

Library layout (one concept, one place):

- ``rigbuild.rig``            the internal blendshape rig representation (:class:`Rig`).
- ``rigbuild.camera``         pinhole + Brown distortion camera model (:class:`Camera`).
- ``rigbuild.geometry``       rigid/similarity fits, mesh operators shared by the stages.
- ``rigbuild.io``             every file format (atomic writes, rigs, cameras, C3D, metrics).
- ``rigbuild.synth``          synthetic capture sessions with ground truth.
- ``rigbuild.calibrate``      ChArUco / chessboard rig calibration.
- ``rigbuild.reconstruct``    CPU multi-view stereo and fusion.
- ``rigbuild.track``          coarse-to-fine Laplacian tracking (Ma et al. 2016, sec. 2).
- ``rigbuild.personalize``    EM blendshape personalization (Ma et al. 2016, sec. 3).
- ``rigbuild.retarget``       Ribera et al. 2017 and Seol et al. 2012 retargeting.
- ``rigbuild.eval``           errors against ground truth (never used by pipeline stages).

Units are millimetres in world space unless a file says otherwise.
"""

__version__ = "0.1.0"
