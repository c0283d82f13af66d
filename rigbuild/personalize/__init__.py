"""EM blendshape personalization (Ma et al. 2016, sections 3-4).

- :mod:`.weights`: per-frame weight QP (box [0, 1], squared-L1 sparsity, temporal smoothness).
- :mod:`.rigid`: per-frame rigid motion (weighted Kabsch with the confidence M).
- :mod:`.shapes`: the shape update (eq. 5-7) with the neutral column, local support, CHOLMOD.
- :mod:`.em`: the EM loop (:func:`personalize`) and held-out fitting (:func:`fit_weights_and_rigid`).
- :mod:`.stage`: the pipeline stage (files in, files out); :mod:`.plots`: report figures.

Deformation transfer for the initial rig D* is :func:`rigbuild.geometry.deformation_transfer.deformation_transfer`.
"""

from rigbuild.personalize.em import PersonalizationResult, PersonalizeParams, fit_weights_and_rigid, personalize

__all__ = ["PersonalizationResult", "PersonalizeParams", "fit_weights_and_rigid", "personalize"]
