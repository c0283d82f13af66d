"""rigbuild: multi-camera facial capture -> personalized blendshape rig -> retargeted animation.

Library layout (one concept, one place):

- ``rigbuild.rig``            the internal blendshape rig representation (:class:`Rig`).
- ``rigbuild.camera``         pinhole + Brown distortion camera model (:class:`Camera`).
- ``rigbuild.geometry``       rigid/similarity fits, mesh operators shared by the stages.
- ``rigbuild.io``             every file format (atomic writes, rigs, cameras, C3D, metrics fragments).
- ``rigbuild.params``         the per-stage parameter checks shared by every ``<stage>/params.py``.
- ``rigbuild.assets``         production data: the procedural head rig and the marker sets.
- ``rigbuild.calibrate``      ChArUco / chessboard rig calibration.
- ``rigbuild.reconstruct``    CPU multi-view stereo and fusion.
- ``rigbuild.track``          coarse-to-fine Laplacian tracking (Ma et al. 2016, sec. 2).
- ``rigbuild.personalize``    EM blendshape personalization (Ma et al. 2016, sec. 3).
- ``rigbuild.retarget``       Ribera et al. 2017 and Seol et al. 2012 retargeting.
  Each stage package has ``params.py`` (its typed ``params.<stage>`` block) and ``stage.py`` (the rules' runners).
- ``rigbuild.eval``           errors against ground truth (run by the evaluation rules, never by a stage job).
- ``rigbuild.synth``          the test-data generator: synthetic capture sessions with ground truth.
- ``rigbuild.render``         the renderers the generator and the previews use.
- ``rigbuild.report``         the session report, its pass / warn / fail limits and the metrics table.

Units are millimetres in world space unless a file says otherwise.
"""

__version__ = "0.1.0"
