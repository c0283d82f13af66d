"""Pictures side by side: the stages' per-camera montages (reconstruction coverage, tracking overlays)."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def tile_images(images: Sequence[np.ndarray], columns: int) -> np.ndarray:
    """(rows * H, columns * W, 3) uint8: images of one size (H, W, 3) uint8 in a grid of ``columns``,
    row-major; cells without an image stay black."""
    h, w = images[0].shape[:2]
    rows = -(-len(images) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = img
    return sheet
