"""Each track's least-squares window: the windows of the image pairs that matched it (out-of-focus pairs match with
larger ones), which the refinement's window-curvature correction then uses per point."""

import numpy as np
import pytest

from recon_engine.matching import MatchingConfig
from recon_engine.tracking import track_windows

NAN = np.nan


def test_it_gives_each_track_its_pairs_windows():
    cfg = MatchingConfig()  # 9 px in focus, 15 px where a pair's blurrier image reads above 0.8 px
    tracks = np.array([
        [[1, 1], [2, 2], [NAN, NAN], [NAN, NAN]],  # pair 0-1: in focus
        [[NAN, NAN], [NAN, NAN], [3, 3], [4, 4]],  # pair 2-3: image 3 blurred
        [[1, 1], [2, 2], [3, 3], [NAN, NAN]],  # pairs 0-1 and 1-2: in focus
        [[NAN, NAN], [2, 2], [NAN, NAN], [4, 4]],  # skip pair 1-3: image 3 blurred
        [[NAN, NAN], [2, 2], [3, 3], [4, 4]],  # pairs 1-2 (in focus) and 2-3 (blurred)
    ], dtype=float)
    blur = np.array([0.6, 0.7, 0.7, 1.1])
    w = track_windows(tracks, blur, cfg)
    assert w == pytest.approx([9, 15, 9, 15, np.sqrt((81 + 225) / 2)])
    assert track_windows(tracks, np.full(4, 0.6), cfg) == pytest.approx(np.full(5, 9.0))  # all in focus: as before
    assert tracks[0, 2, 0] != tracks[0, 2, 0]  # the input is not modified (its NaNs stay)
