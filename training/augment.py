"""Training-time augmentation of the camera input (ours, in `train fit --arch ours`; the paper
names none).

Zoom-out: the camera image is shrunk about its centre by a factor s <= 1 and the margin filled
by repeating the edge pixels. The shrunk picture is what a camera on the same optical axis with
s times the focal length (a wider view) sees in the middle: everything looks 1/s times as far
away. It exists for the traffic lights (issue 13): at a junction the only signal head in view
is the one across it, and the width of the junction sets how small its lamp looks. Trained on
towns with two-lane junctions, the tiny model's camera-only red-light head found 46 % of
downtown's red lights as recorded and 4 % with the image shrunk to 0.55, and missed those of a
town with three-lane arterials, whose governing lamps are 1.5-2 px wide. The labels do not
change: they are distances along the road and states, not pixels.
"""

from __future__ import annotations

import zlib

import cv2
import numpy as np


def zoom_out(image: np.ndarray, scale: float) -> np.ndarray:
    """(3, H, W) uint8 RGB -> the same shape: the picture shrunk by `scale` (0 < scale <= 1)
    about its centre (area interpolation), the margin the edge pixels repeated."""
    if scale >= 1.0:
        return image
    _, h, w = image.shape
    sh, sw = max(1, round(h * scale)), max(1, round(w * scale))
    small = cv2.resize(image.transpose(1, 2, 0), (sw, sh), interpolation=cv2.INTER_AREA)
    top, left = (h - sh) // 2, (w - sw) // 2
    out = cv2.copyMakeBorder(small, top, h - sh - top, left, w - sw - left, cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(out.transpose(2, 0, 1))


def zoom_scale(
    seed: int, epoch: int, episode_id: str, frame: int, smallest: float, probability: float
) -> float:
    """The zoom-out factor of one frame in one epoch: 1 (no zoom) with probability
    1 - `probability`, else uniform in [`smallest`, 1). A function of its arguments only, so a
    resumed run and any number of workers draw the same factors."""
    key = [seed, epoch, zlib.crc32(episode_id.encode()), frame]
    rng = np.random.default_rng(key)
    u, s = rng.random(2)
    return float(smallest + (1.0 - smallest) * s) if u < probability else 1.0
