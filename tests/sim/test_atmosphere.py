"""The atmosphere screen is sampled exactly as bilinear interpolation with edge extension."""
import numpy as np
from scipy import ndimage

from so_transients.sim.atmosphere import _sample_screen


def test_screen_sampling_equals_scipy_bilinear_interpolation():
    rng = np.random.default_rng(4)
    field = rng.standard_normal((8, 12)).astype(np.float32)
    x0, y0, pix = -8.0, -5.0, 0.5
    t = np.linspace(0, 30, 500)
    az = np.radians(180 + 40 * np.sin(t / 5))
    daz, el = np.radians([0.0, 1.3, -2.0]), np.radians([50.0, 49.0, 51.5])
    reach = 12.0 / np.tan(el)            # lines of sight that leave the field on some sides
    wx, wy = 0.4, -0.3
    out = np.empty((3, len(t)), np.float32)
    _sample_screen(field, (x0, y0, pix), wx, wy, reach, np.sin(daz), np.cos(daz), t,
                   np.sin(az), np.cos(az), out)
    x = reach[:, None] * np.sin(az + daz[:, None]) - wx * t
    y = reach[:, None] * np.cos(az + daz[:, None]) - wy * t
    rows, cols = (y - y0) / pix, (x - x0) / pix
    ny, nx = field.shape
    for beyond in (rows < 0, rows > ny - 1, cols < 0, cols > nx - 1):
        assert 0.01 < beyond.mean() < 0.9    # inside and beyond each edge
    expect = ndimage.map_coordinates(field, [rows.ravel(), cols.ravel()], order=1,
                                     mode="nearest").reshape(rows.shape)
    assert np.allclose(out, expect, atol=1e-5)
