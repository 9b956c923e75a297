"""The projector pattern follows the paper's rules."""

import numpy as np

from recon_engine.pattern import BLOCK, N_BLOCKS, make_pattern, repeats_within_radius


def test_the_eleven_blocks_are_distinct():
    _, blocks, layout = make_pattern(300, 200, seed=3)
    assert blocks.shape == (N_BLOCKS, 3, 3)
    flat = blocks.reshape(N_BLOCKS, -1)
    assert len({row.tobytes() for row in flat}) == N_BLOCKS
    assert set(np.unique(layout)) == set(range(N_BLOCKS))


def test_no_block_repeats_within_six_pixels_anywhere():
    image, blocks, layout = make_pattern(1024, 768, seed=11)
    assert repeats_within_radius(layout, 6.0) == 0
    # and the check itself finds repeats where there are some
    bad = layout.copy()
    bad[10, 12] = bad[10, 10]  # two blocks apart: 6 px between centres
    assert repeats_within_radius(bad, 6.0) >= 1


def test_image_is_the_layout_of_blocks():
    image, blocks, layout = make_pattern(31, 20, seed=5)
    assert image.shape == (20, 31)
    i, j = 4, 7
    assert np.array_equal(image[i * BLOCK:(i + 1) * BLOCK, j * BLOCK:(j + 1) * BLOCK], blocks[layout[i, j]])


def test_it_is_deterministic_from_the_seed():
    a = make_pattern(200, 100, seed=7)[0]
    b = make_pattern(200, 100, seed=7)[0]
    c = make_pattern(200, 100, seed=8)[0]
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_radius_rule_holds_at_other_resolutions_and_seeds():
    for seed, (w, h) in enumerate([(64, 48), (640, 480), (1280, 800)]):
        _, _, layout = make_pattern(w, h, seed=seed)
        assert repeats_within_radius(layout) == 0
