"""Per-frame multi-view stereo on the CPU (issue 4).

- :mod:`.params` - the stage's parameters (:class:`ReconstructParams`, :class:`StereoParams`).
- :mod:`.stereo` - coarse-to-fine plane sweep with NCC over neighbour views, sub-pixel refinement.
- :mod:`.masks` - background masking, bad-image detection.
- :mod:`.filter` - multi-view depth consistency and per-pixel fusion.
- :mod:`.consistency` - the cross-view disagreement of the stereo's depth (the stage's gate, no ground truth).
- :mod:`.fuse` - oriented point cloud, Poisson / TSDF surface, crop to the head.
- :mod:`.frame` - one frame end to end (:func:`reconstruct_frame`).
- :mod:`.sequence` - a ROM sequence: frame outputs, bad frames, the coverage summary.
- :mod:`.renders` - the report's pictures: depth and shaded mesh at the neutral and the peak frame.
- :mod:`.stage` - the Snakemake runners (frame job, sequence summary, session pooling).
- :mod:`.lift` - :func:`depth_at`: 2-D image points -> 3-D through a depth map (for tracking).

The names below are imported on first use, so ``rigbuild.reconstruct.params`` stays cheap to import.
"""

import importlib

_EXPORTS = {"FrameReconstruction": "frame", "reconstruct_frame": "frame", "ReconstructParams": "params",
            "StereoParams": "params", "depth_at": "lift"}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"rigbuild.reconstruct.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'rigbuild.reconstruct' has no attribute {name!r}")
