"""Heights of the reference's own points: local planes, exact on planes, sharp at steps."""

import numpy as np

from tiereg.surface import LocalSurface


def _grid(f, spacing=1.0, half=50.0):
    g = np.arange(-half, half, spacing)
    gx, gy = np.meshgrid(g, g)
    return np.column_stack([gx.ravel(), gy.ravel(), f(gx.ravel(), gy.ravel())])


def test_heights_on_a_tilted_plane_are_exact():
    def plane(x, y):
        return 0.1 * x - 0.2 * y + 5.0

    surface = LocalSurface(_grid(plane), radius=3.0)
    xy = np.random.default_rng(0).uniform(-40, 40, (500, 2))
    np.testing.assert_allclose(surface.heights(xy[:, 0], xy[:, 1]), plane(xy[:, 0], xy[:, 1]),
                               atol=1e-9)


def test_heights_beside_a_step_are_those_of_its_side():
    # a 10 m high block (a building) from x = 0 on; points 2 m either side of its wall get the
    # roof's and the ground's height, not the mix a 5 m grid cell would give
    def step(x, y):
        return np.where(x >= 0, 10.0, 0.0)

    surface = LocalSurface(_grid(step, spacing=0.5), radius=2.0)
    z = surface.heights(np.array([2.0, -2.0, 20.0]), np.array([0.0, 5.0, -30.0]))
    np.testing.assert_allclose(z, [10.0, 0.0, 10.0], atol=1e-9)


def test_no_height_off_the_points():
    surface = LocalSurface(_grid(lambda x, y: x * 0.0), radius=3.0)
    assert np.isnan(surface.heights(np.array([500.0]), np.array([0.0]))).all()


def test_at_a_wall_the_visible_surface_wins_whatever_the_order():
    # two returns at one position (a wall's top and foot): the height is the top's, in any order
    pts = _grid(lambda x, y: np.where(x >= 0, 10.0, 0.0), spacing=1.0, half=5.0)
    wall = np.array([[0.2, 0.0, 0.0], [0.2, 0.0, 10.0]])
    for order in (wall, wall[::-1]):
        surface = LocalSurface(np.vstack([order, pts]), radius=3.0)
        assert surface.heights(np.array([0.25]), np.array([0.0]))[0] == 10.0
