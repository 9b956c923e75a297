"""Small image utilities shared by the engine's stages."""

from __future__ import annotations

import cv2
import numpy as np

_COLS = 4096  # cv2.remap needs both map dimensions below 32767


def sample_bilinear(image: np.ndarray, x, y, border: str = "constant", value: float = 0.0,
                    interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Bilinear samples of an ``image`` at pixel positions ``x``, ``y`` (OpenCV's remap: positions rounded to 1/32 px).

    Positions follow OpenCV's convention (centre of the top-left pixel at
    (0, 0)); any shape, returned in the same shape as float32 (with a last
    axis of C for an (H, W, C) image of up to 4 channels). ``interpolation``
    may ask for another of OpenCV's, e.g. ``cv2.INTER_NEAREST``.
    """
    x = np.asarray(x, dtype=np.float32)
    shape = x.shape
    x = x.ravel()
    y = np.asarray(y, dtype=np.float32).ravel()
    n = len(x)
    channels = image.shape[2:] if image.ndim == 3 else ()
    if n == 0:
        return np.zeros(shape + channels, np.float32)
    rows = -(-n // _COLS)
    pad = rows * _COLS - n
    mapx = np.concatenate([x, np.full(pad, -10.0, np.float32)]).reshape(rows, _COLS)
    mapy = np.concatenate([y, np.full(pad, -10.0, np.float32)]).reshape(rows, _COLS)
    mode = cv2.BORDER_CONSTANT if border == "constant" else cv2.BORDER_REPLICATE
    src = image if image.dtype in (np.float32, np.uint8) else image.astype(np.float32)
    out = cv2.remap(src, mapx, mapy, interpolation, borderMode=mode, borderValue=value)
    return out.reshape((-1,) + channels)[:n].astype(np.float32).reshape(shape + channels)
