"""Process-level settings of the engine's stages."""

import platform

import numpy as np
import pytest

from recon_engine.parallel import cores, reuse_freed_images


def test_cores_is_the_request_or_one_per_core():
    assert cores(3) == 3
    assert cores(0) >= 1


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_it_keeps_freed_large_images_for_reuse():
    assert reuse_freed_images() is True
    # large blocks still allocate, free and come back intact
    for _ in range(3):
        a = np.ones((2000, 3000, 4), np.float32)
        assert float(a[-1, -1, -1]) == 1.0
        del a
