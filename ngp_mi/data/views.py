"""The views and lights of datasets and comparisons, seeded so that any one can be reproduced alone.

Seeds derive from (seed, shape index[, view]) (:func:`derived_seed`), never from the order of work,
so shards, worker processes and resumed runs see the same cameras and lights.
"""

from __future__ import annotations

import functools

import numpy as np

from ngp_mi.camera import Camera, ViewDistribution
from ngp_mi.lights import DirectionalLight, Light, overhead_rig

LIGHT_MODES = ("rig", "random", "scene")


def derived_seed(*keys: int) -> int:
    """A 32-bit seed from integer keys (``numpy.random.SeedSequence``): stable across runs and shards."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1)[0])


def view_cameras(views: int, resolution: int, seed: int, shape_index: int,
                 distribution: ViewDistribution = ViewDistribution()) -> list[Camera]:
    """The ``views`` cameras of shape ``shape_index``: drawn from ``distribution`` with a seed of
    (seed, shape index)."""
    return distribution.sample(views, seed=derived_seed(seed, shape_index), resolution=resolution)


@functools.lru_cache(maxsize=1)
def _rig() -> tuple[Light, ...]:
    return tuple(overhead_rig())  # the same for every view: built once (~10 % of a view's time in a profile)


def random_lights(seed: int, shape_index: int, view: int) -> list[Light]:
    """1–4 white-ish directional lights above the horizon, seeded by (seed, shape index, view)."""
    rng = np.random.default_rng([seed, shape_index, view, 7])
    lights = []
    for _ in range(int(rng.integers(1, 5))):
        el, az = np.radians(rng.uniform(15, 85)), rng.uniform(0, 2 * np.pi)
        colour = rng.uniform(0.8, 1.0, 3) * rng.uniform(0.3, 1.5)
        lights.append(DirectionalLight((np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)), tuple(colour)))
    return lights


def view_lights(mode: str, seed: int, shape_index: int, view: int) -> list[Light]:
    """The lights of one view: the overhead rig (``rig``, and ``scene`` where the scene has none of
    its own to use) or :func:`random_lights` (``random``)."""
    if mode not in LIGHT_MODES:
        raise ValueError(f"lights must be one of {LIGHT_MODES}, got {mode!r}")
    return random_lights(seed, shape_index, view) if mode == "random" else list(_rig())
