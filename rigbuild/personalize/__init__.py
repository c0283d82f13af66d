"""EM blendshape personalization (Ma et al. 2016, sections 3-4).

- :mod:`.weights`: per-frame weight QP (box [0, 1], squared-L1 sparsity, temporal smoothness).
- :mod:`.rigid`: per-frame rigid motion (weighted Kabsch with the confidence M).
- :mod:`.shapes`: the shape update (eq. 5-7) with the neutral column, local support, CHOLMOD.
- :mod:`.em`: the EM loop (:func:`personalize`) and held-out fitting (:func:`fit_weights_and_rigid`).
- :mod:`.params`: the typed ``params.personalize`` block (:class:`~.params.PersonalizeParams` for the EM,
  :class:`~.params.PersonalizeConfig` with the stage options, :func:`~.params.from_config`).
- :mod:`.stage`: the pipeline stage (files in, files out); :mod:`.plots`: report figures.

Deformation transfer for the initial rig D* is :func:`rigbuild.geometry.deformation_transfer.deformation_transfer`.
"""

from importlib import import_module

#: public names -> the module defining them (imported on first use, so that importing
#: ``rigbuild.personalize.params`` at DAG start does not load the solver's scipy stack)
_EXPORTS = {"PersonalizationResult": "em", "fit_weights_and_rigid": "em", "personalize": "em",
            "PersonalizeParams": "params", "PersonalizeConfig": "params", "from_config": "params"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"rigbuild.personalize.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'rigbuild.personalize' has no attribute {name!r}")
