"""The projector pattern: random arrangement of eleven unique 3x3 binary blocks.

The paper's pattern (Detchev, Habib and Chang) tiles the projector frame with
3x3-pixel binary sub-blocks, eleven distinct ones placed at random so that no
sub-block appears twice within a six-pixel radius. Locally the texture is then
unique along any epipolar line segment a matcher searches, while the frame as
a whole stays dense in edges for corner detection.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BLOCK", "N_BLOCKS", "REPEAT_RADIUS_PX", "make_blocks", "make_layout", "make_pattern"]

BLOCK = 3  # side of a sub-block (projector px)
N_BLOCKS = 11  # distinct sub-blocks
REPEAT_RADIUS_PX = 6.0  # no sub-block repeats with its centre this close (projector px)


def _neighbour_offsets(radius_px: float = REPEAT_RADIUS_PX, block: int = BLOCK):
    """Block-grid offsets (di, dj) whose centres lie within ``radius_px``."""
    r = int(np.floor(radius_px / block))
    di, dj = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    keep = (block * np.hypot(di, dj) <= radius_px + 1e-9) & ((di != 0) | (dj != 0))
    return np.column_stack([di[keep], dj[keep]])


def make_blocks(rng: np.random.Generator, n_blocks: int = N_BLOCKS, min_hamming: int = 3) -> np.ndarray:
    """``n_blocks`` distinct 3x3 binary blocks (n, 3, 3) of uint8 0/1.

    Each block has 3 to 6 lit pixels (neither nearly dark nor nearly white, so
    every block carries edges) and any two blocks differ in at least
    ``min_hamming`` pixels, so a block is recognisable even when blurred.
    """
    codes = np.arange(512)
    bits = ((codes[:, None] >> np.arange(9)) & 1).astype(np.uint8)
    ones = bits.sum(1)
    candidates = bits[(ones >= 3) & (ones <= 6)]
    for _ in range(1000):
        order = rng.permutation(len(candidates))
        chosen = []
        for idx in order:
            b = candidates[idx]
            if all(np.sum(b != c) >= min_hamming for c in chosen):
                chosen.append(b)
                if len(chosen) == n_blocks:
                    return np.stack(chosen).reshape(n_blocks, BLOCK, BLOCK)
    raise RuntimeError("could not draw distinct pattern blocks")  # pragma: no cover


def make_layout(shape_blocks, rng: np.random.Generator, n_blocks: int = N_BLOCKS,
                radius_px: float = REPEAT_RADIUS_PX) -> np.ndarray:
    """Random block indices (rows, cols) with no index repeated within ``radius_px``.

    Filled in raster order: each cell draws uniformly among the indices not used
    by the already-filled cells within the radius. With the default radius a
    cell has 6 filled neighbours and 11 indices to choose from, so a choice
    always exists. Rows are filled vectorized across every other column pair.
    """
    rows, cols = shape_blocks
    offsets = _neighbour_offsets(radius_px)
    # cells before (i, j) in raster order: the constraints known when (i, j) is drawn
    causal = offsets[(offsets[:, 0] < 0) | ((offsets[:, 0] == 0) & (offsets[:, 1] < 0))]
    reach = int(np.max(np.abs(offsets)))
    if len(causal) >= n_blocks:
        raise ValueError(f"{n_blocks} blocks cannot avoid repeats within {radius_px} px")
    pad = reach
    layout = np.full((rows + 2 * pad, cols + 2 * pad), -1, dtype=np.int16)
    # within one row, cells at column distance > reach do not constrain each
    # other, so fill the row in (reach + 1) interleaved passes, each vectorized.
    for i in range(rows):
        for start in range(reach + 1):
            js = np.arange(start, cols, reach + 1)
            used = np.zeros((len(js), n_blocks), dtype=bool)
            for di, dj in causal:
                nb = layout[pad + i + di, pad + js + dj]
                ok = nb >= 0
                used[np.flatnonzero(ok), nb[ok]] = True
            # cells of this pass also neighbour later cells of the same row
            # at dj in (0, reach]: those are filled in later passes, which see them.
            for dj in range(1, reach + 1):
                nb = layout[pad + i, pad + js + dj]
                ok = nb >= 0
                used[np.flatnonzero(ok), nb[ok]] = True
            scores = rng.random((len(js), n_blocks))
            scores[used] = -1.0
            layout[pad + i, pad + js] = np.argmax(scores, axis=1)
    return layout[pad:pad + rows, pad:pad + cols].astype(np.int16)


def make_pattern(width: int, height: int, seed: int = 0, n_blocks: int = N_BLOCKS,
                 radius_px: float = REPEAT_RADIUS_PX):
    """The projector image (height, width) of float32 0/1 and its block layout.

    Parameters
    ----------
    width, height : int
        Projector resolution (projector px).
    seed : int
        The same seed always gives the same pattern.

    Returns
    -------
    image : (height, width) float32 array, 1 where the projector pixel is lit
    blocks : (n_blocks, 3, 3) uint8 array of the distinct sub-blocks
    layout : (ceil(height / 3), ceil(width / 3)) int16 array of block indices
    """
    rng = np.random.default_rng(seed)
    blocks = make_blocks(rng, n_blocks)
    rows, cols = -(-height // BLOCK), -(-width // BLOCK)
    layout = make_layout((rows, cols), rng, n_blocks, radius_px)
    tiles = blocks[layout]  # (rows, cols, 3, 3)
    image = tiles.transpose(0, 2, 1, 3).reshape(rows * BLOCK, cols * BLOCK)[:height, :width]
    return image.astype(np.float32), blocks, layout


def repeats_within_radius(layout: np.ndarray, radius_px: float = REPEAT_RADIUS_PX) -> int:
    """Number of block pairs with the same index whose centres lie within ``radius_px``."""
    count = 0
    rows, cols = layout.shape
    for di, dj in _neighbour_offsets(radius_px):
        if (di, dj) <= (0, 0):
            continue  # count each unordered pair once
        a = layout[max(0, -di):rows - max(0, di), max(0, -dj):cols - max(0, dj)]
        b = layout[max(0, di):rows + min(0, di), max(0, dj):cols + min(0, dj)]
        count += int(np.sum(a == b))
    return count
