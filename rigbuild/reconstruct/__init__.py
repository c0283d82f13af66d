"""Per-frame multi-view stereo on the CPU (issue 4).

- :mod:`.stereo` - coarse-to-fine plane sweep with NCC over neighbour views, sub-pixel refinement.
- :mod:`.masks` - background masking, bad-image detection.
- :mod:`.filter` - multi-view depth consistency and per-pixel fusion.
- :mod:`.fuse` - oriented point cloud, Poisson / TSDF surface, crop to the head.
- :mod:`.frame` - one frame end to end (:func:`reconstruct_frame`, :class:`ReconstructParams`).
- :mod:`.sequence` - a ROM sequence and the Snakemake stage (outputs, bad frames, metrics).
- :mod:`.lift` - :func:`depth_at`: 2-D image points -> 3-D through a depth map (for tracking).
"""

from rigbuild.reconstruct.frame import FrameReconstruction, ReconstructParams, reconstruct_frame
from rigbuild.reconstruct.lift import depth_at
from rigbuild.reconstruct.stereo import StereoParams

__all__ = ["FrameReconstruction", "ReconstructParams", "StereoParams", "depth_at", "reconstruct_frame"]
