"""The partial-view perturbation: each flower's disc cut by a seeded plane, removing the share
of it the cut says and nothing outside the flower."""

import numpy as np
import pytest

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.perturb import Perturbation, cut, draw_cuts, perturb, segment_offset


def _disc(centre, normal, radius, count, rng):
    """Points spread evenly over a flat disc, and a patch of leaf well outside it."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    r = radius * np.sqrt(rng.uniform(0, 1, count))
    t = rng.uniform(0, 2 * np.pi, count)
    return centre + np.outer(r * np.cos(t), u) + np.outer(r * np.sin(t), v)


@pytest.mark.parametrize("share", [0.25, 0.5, 0.75])
def test_a_cut_removes_its_share_of_each_disc_and_nothing_beyond(share):
    rng = np.random.default_rng(0)
    flowers = [(np.array([0.0, 0.0, 0.3]), np.array([0.0, 0.0, 1.0]), 0.02),
               (np.array([0.1, 0.0, 0.25]), np.array([1.0, 0.2, 0.3]), 0.015)]
    discs = [_disc(c, n, r, 20000, rng) for c, n, r in flowers]
    leaf = rng.uniform([-0.2, 0.2, 0.0], [0.2, 0.4, 0.1], (500, 3))
    points = np.vstack([*discs, leaf])
    cloud = Cloud(points, np.full((len(points), 3), 200, np.uint8))
    cuts = draw_cuts(flowers, share, np.random.default_rng(3))
    kept = cut(cloud, cuts)
    removed = np.setdiff1d(np.arange(len(points)), _indices(cloud, kept))
    for k, disc in enumerate(discs):
        start = sum(len(d) for d in discs[:k])
        gone = np.isin(np.arange(start, start + len(disc)), removed).mean()
        assert gone == pytest.approx(share, abs=0.015)
        # What went lies on one side of a line across the disc, at the cut's offset.
        side = (disc - flowers[k][0]) @ cuts[k].direction
        assert abs(cuts[k].direction @ flowers[k][1] / np.linalg.norm(flowers[k][1])) < 1e-9
        assert side[np.isin(np.arange(start, start + len(disc)), removed)].min() >= \
            cuts[k].offset - 1e-12
    assert not np.isin(np.arange(len(points) - len(leaf), len(points)), removed).any()


def _indices(cloud: Cloud, kept: Cloud) -> np.ndarray:
    lookup = {tuple(p): k for k, p in enumerate(cloud.points)}
    return np.array([lookup[tuple(p)] for p in kept.points])


def test_a_cut_is_seeded_the_same_for_every_file_and_needs_its_flowers():
    flowers = [(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.02)]
    first = draw_cuts(flowers, 0.5, np.random.default_rng(5))
    again = draw_cuts(flowers, 0.5, np.random.default_rng(5))
    other = draw_cuts(flowers, 0.5, np.random.default_rng(6))
    assert np.allclose(first[0].direction, again[0].direction)
    assert not np.allclose(first[0].direction, other[0].direction)
    assert segment_offset(0.5) == pytest.approx(0.0, abs=1e-9)
    assert segment_offset(0.25) == pytest.approx(0.4040, abs=1e-4)
    cloud = Cloud(np.zeros((3, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(InputError, match="cut"):
        perturb(cloud, Perturbation("cut", 0.25), np.random.default_rng(0))
    with pytest.raises(InputError, match="cut"):
        Perturbation("cut", 1.0)
    assert Perturbation("cut", 0.0).is_identity()
