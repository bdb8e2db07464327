"""The BEV grid of the paper (Sec. III-A): 256x256 px, 32 m ahead, 16 m to each side, 8 px/m.

Row 0 is 32 m ahead, the ego sits at the bottom centre; column 0 is 16 m to the left. Pixel
(row, col) covers ego-frame x in (32 - (row+1)/8, 32 - row/8] and y in (16 - (col+1)/8, 16 - col/8].
"""

from __future__ import annotations

import numpy as np

BEV_SIZE_PX = 256
BEV_PX_PER_M = 8.0
BEV_AHEAD_M = 32.0
BEV_SIDE_M = 16.0


def ego_to_bev_px(x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (row, col) pixel coordinates of ego-frame points (x forward, y left, m).

    Integer parts are the pixel indices; points with 0 <= row, col < 256 lie on the grid.
    """
    row = (BEV_AHEAD_M - np.asarray(x_m, dtype=np.float64)) * BEV_PX_PER_M
    col = (BEV_SIDE_M - np.asarray(y_m, dtype=np.float64)) * BEV_PX_PER_M
    return row, col


def bev_pixel_centres() -> tuple[np.ndarray, np.ndarray]:
    """Ego-frame (x, y) in metres of every pixel centre, each of shape (256, 256)."""
    idx = np.arange(BEV_SIZE_PX) + 0.5
    x = BEV_AHEAD_M - idx / BEV_PX_PER_M
    y = BEV_SIDE_M - idx / BEV_PX_PER_M
    return np.repeat(x[:, None], BEV_SIZE_PX, 1), np.repeat(y[None, :], BEV_SIZE_PX, 0)
