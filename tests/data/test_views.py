"""Views and lights of datasets: seeded by (seed, shape, view), never by the order of work."""

import numpy as np
import pytest

from ngp_mi.data.views import derived_seed, random_lights, view_cameras, view_lights
from ngp_mi.lights import overhead_rig


def test_cameras_depend_on_the_shape_index_not_on_the_order():
    a = view_cameras(3, 32, seed=5, shape_index=2)
    view_cameras(3, 32, seed=5, shape_index=7)  # another shape in between changes nothing
    b = view_cameras(3, 32, seed=5, shape_index=2)
    assert [c.E.tolist() for c in a] == [c.E.tolist() for c in b]
    assert a[0].E.tolist() != view_cameras(3, 32, seed=5, shape_index=3)[0].E.tolist()
    assert all(0 <= c.theta_deg <= 20 and -90 <= c.phi_deg <= 90 for c in a)  # the paper's distribution
    assert derived_seed(1, 2) == derived_seed(1, 2) != derived_seed(2, 1)


def test_lights_are_the_rig_or_seeded_random_lights_above_the_horizon():
    assert [l.to_dict() for l in view_lights("rig", 0, 0, 0)] == [l.to_dict() for l in overhead_rig()]
    for view in range(20):
        lights = view_lights("random", 3, 1, view)
        assert 1 <= len(lights) <= 4 and lights == random_lights(3, 1, view)
        assert all(l.direction[1] > 0 and np.isclose(np.linalg.norm(l.direction), 1) for l in lights)
    with pytest.raises(ValueError, match="lights must be one of"):
        view_lights("sun", 0, 0, 0)
