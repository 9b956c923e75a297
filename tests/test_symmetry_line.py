"""The back's line of symmetry is found as one line through the rows: a row whose own best fit lies far off
(a flat, sparse or noisy row) does not pull the line sideways, while a real, gradual deviation is followed."""

import numpy as np

from analysis.backsurface import smoothest_path, symmetry_costs


def back_rows(x0s, x, rng=None, noise_mm=0.0):
    """Rows of a back whose furrow (symmetric about x0) lies at each of ``x0s`` (mm), with a tilt."""
    u = x[None, :] - np.asarray(x0s)[:, None]
    rows = 60.0 + 12.0 * (1 - np.exp(-(u / 25.0) ** 2)) - 0.002 * u ** 2 + 0.05 * u
    if rng is not None:
        rows = rows + rng.normal(0.0, noise_mm, rows.shape)
    return rows


def test_it_finds_each_rows_symmetry_point():
    x = np.arange(-200.0, 200.0 + 1e-9, 2.0)
    truth = np.array([-7.3, 0.0, 4.6, 11.2])
    off, cost = symmetry_costs(x, back_rows(truth, x), np.zeros(4), 40.0, 20.0)
    assert off[0] == -20.0 and off[-1] == 20.0 and cost.shape == (4, len(off))
    assert np.allclose(off[np.argmin(cost, axis=1)], np.round(truth), atol=1.0)
    line = smoothest_path(cost, off, np.zeros(4), 0.0)
    assert np.allclose(line, truth, atol=0.3)


def test_a_row_that_reads_wrong_does_not_pull_the_line():
    rng = np.random.default_rng(3)
    x = np.arange(-200.0, 200.0 + 1e-9, 2.0)
    z = np.arange(0.0, 400.0, 4.0)
    truth = 15.0 * np.sin(np.pi * z / 400.0)  # a C curve: 15 mm at its apex
    rows = back_rows(truth, x, rng, noise_mm=0.05)
    # a band of rows whose furrow is flattened out and whose one side is disturbed: alone, they read far off
    band = (z > 180) & (z < 220)
    rows[band] = back_rows(truth[band] + 25.0, x) * 0.5 + 30.0
    off, cost = symmetry_costs(x, rows, np.zeros(len(z)), 40.0, 50.0)
    alone = off[np.argmin(cost, axis=1)]
    assert np.max(np.abs(alone[band] - truth[band])) > 15.0
    line = smoothest_path(cost, off, np.zeros(len(z)), 0.3)
    assert np.max(np.abs(line - truth)) < 5.0
    assert np.max(np.abs(line[~band] - truth[~band])) < 1.0  # the real curve is followed, not flattened


def test_rows_without_skin_give_no_point_and_do_not_break_the_line():
    x = np.arange(-200.0, 200.0 + 1e-9, 2.0)
    truth = np.linspace(-5.0, 5.0, 30)
    rows = back_rows(truth, x)
    rows[10:13] = np.nan
    off, cost = symmetry_costs(x, rows, np.zeros(30), 40.0, 20.0)
    line = smoothest_path(cost, off, np.zeros(30), 0.3)
    assert np.isnan(line[10:13]).all()
    keep = np.isfinite(line)
    assert np.max(np.abs(line[keep] - truth[keep])) < 0.5
