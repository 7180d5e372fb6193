"""The operating envelope: sparse, scaled, cast and perturbed clouds give the same flowers."""

import logging

import numpy as np
import pytest
from candidate_flowers import PISTIL, candidate_flowers

from flowerpose.cloudio import Cloud, to_metres
from flowerpose.config import apply_overrides
from flowerpose.perturb import Perturbation, channel_gain, parse_perturbation, perturb, relit
from flowerpose.pipeline.cluster_config import ClusterConfig, OutlierConfig, for_cloud
from flowerpose.pipeline.colour import ColourConfig, white_gain
from flowerpose.pipeline.fit import fit_plane
from flowerpose.pipeline.flowers import PipelineConfig, find_flowers_in_candidates
from flowerpose.pipeline.limits import COUNT_FLOORS, Density


def _matched(cloud: Cloud, centres: np.ndarray, normals: np.ndarray,
             config: PipelineConfig | None = None) -> dict[int, float]:
    """Truth flower -> plane error (degrees) of the flowers found within 5 mm of it."""
    found = {}
    for flower in find_flowers_in_candidates(cloud, config or PipelineConfig()).flowers:
        distance = np.linalg.norm(centres - flower.pose.center, axis=1)
        if distance.min() < 0.005 * max(1.0, np.ptp(centres) / 0.4):
            normal = flower.pose.normals["plane"]
            found[int(distance.argmin())] = float(np.degrees(np.arccos(np.clip(
                normal @ normals[distance.argmin()], -1, 1))))
    return found


@pytest.mark.parametrize("seed", [0, 1])
def test_flowers_of_60_points_are_found_and_posed(seed):
    cloud, centres, normals = candidate_flowers(60, seed)
    found = _matched(cloud, centres, normals)
    assert sorted(found) == list(range(len(centres)))
    assert max(found.values()) < 10.0
    # Counts stated for one density (the paper's) find none of them.
    stated = apply_overrides(PipelineConfig(), {"cluster": {"density_reference": "none"}})
    assert _matched(cloud, centres, normals, stated) == {}


def _without_pistil(cloud: Cloud, centre: np.ndarray) -> Cloud:
    """The cloud without the pistil-coloured points of the flower at `centre`."""
    yellow = ((cloud.colors == PISTIL).all(axis=1)
              & (np.linalg.norm(cloud.points - centre, axis=1) < 0.03))
    return cloud.subset(np.flatnonzero(~yellow))


@pytest.mark.parametrize("seed", [4, 6])
def test_a_flower_whose_pistil_is_not_seen_counts_only_in_a_sparse_cloud(seed):
    # Sparse, a receptacle shows as a handful of points or none, and a corolla whose
    # sepals orient it is a flower; dense, a corolla without one is not (sheen, stereo
    # fringe). (Seeds whose crop takes in enough of the sepals to orient it.)
    for points, kept in ((60, True), (1500, False)):
        cloud, centres, normals = candidate_flowers(points, seed)
        found = _matched(_without_pistil(cloud, centres[2]), centres, normals)
        assert sorted(set(found) - {2}) == [0, 1, 3, 4, 5]
        assert (2 in found) == kept
        if kept:  # oriented by its sepals
            assert found[2] < 10.0
    always = apply_overrides(PipelineConfig(), {"cluster": {"pistil_optional_density": 0}})
    sparse, centres, normals = candidate_flowers(60, seed)
    assert 2 not in _matched(_without_pistil(sparse, centres[2]), centres, normals, always)


def test_a_cloud_in_millimetres_and_in_metres_give_the_same_flowers():
    cloud, centres, normals = candidate_flowers(120, seed=2)
    metres = _matched(cloud, centres, normals)
    millimetres = Cloud(to_metres(cloud.points * 1000, "mm", "test"), cloud.colors)
    assert _matched(millimetres, centres, normals) == pytest.approx(metres, abs=1e-6)
    # Photogrammetry's own unit (a unit of 4 cm), said as metres a unit ...
    own = Cloud(to_metres(cloud.points * 25, 0.04, "test"), cloud.colors)
    assert _matched(own, centres, normals) == pytest.approx(metres, abs=1e-6)
    # ... or not said at all: the limits follow the flowers' measured size.
    scaled = _matched(Cloud(cloud.points * 1000, cloud.colors), centres * 1000, normals)
    assert sorted(scaled) == sorted(metres) and max(scaled.values()) < 10.0


def test_a_colour_cast_of_15_percent_is_removed():
    cloud, centres, normals = candidate_flowers(200, seed=3)
    plain = _matched(cloud, centres, normals)
    neutral = white_gain(cloud.colors, ColourConfig())  # the petals' own slight tint
    for channel in "rgb":
        for change in (-0.15, 0.15):
            cast = relit(cloud, channel_gain(channel=channel, cast=change))
            gain = white_gain(cast.colors, ColourConfig())
            # The gain undoes the cast, up to the mean it keeps.
            undone = channel_gain(channel=channel, cast=change) * gain / neutral
            assert np.ptp(undone) < 0.02
            assert sorted(_matched(cast, centres, normals)) == sorted(plain)


def test_a_perturbation_is_reproducible_from_its_seed():
    cloud, _, _ = candidate_flowers(300, seed=4)
    for perturbation in (Perturbation("thin", 0.3), Perturbation("noise", 0.001)):
        first = perturb(cloud, perturbation, np.random.default_rng([7, 1]))
        again = perturb(cloud, perturbation, np.random.default_rng([7, 1]))
        other = perturb(cloud, perturbation, np.random.default_rng([8, 1]))
        assert np.array_equal(first.points, again.points)
        assert not np.array_equal(first.points, other.points)
    assert parse_perturbation("cast=b+0.15") == Perturbation("cast", 0.15, "b")
    assert parse_perturbation("thin=0.1").label == "thin 0.1"


@pytest.mark.parametrize("text", ["thin=0", "thin=1.5", "exposure=-1", "cast=0.1",
                                  "noise=-0.001", "drop_view=1.5", "blur=2", "thin"])
def test_a_bad_perturbation_is_one_clear_error(text):
    from flowerpose.errors import InputError

    with pytest.raises(InputError):
        parse_perturbation(text)


def test_counts_follow_the_density_down_to_their_floors_and_never_up():
    outliers, cluster = OutlierConfig(), ClusterConfig()
    _, dense, density = for_cloud(outliers, cluster, 1.0, spacing=0.0005)
    assert density.factor == 1.0 and dense.min_points == cluster.min_points
    _, sparse, density = for_cloud(outliers, cluster, 1.0, spacing=0.004)
    assert 0 < density.factor < 1
    assert COUNT_FLOORS["min_points"] <= sparse.min_points < cluster.min_points
    assert sparse.split_link_m >= 2 * 0.004 and sparse.eps >= 2.5 * 0.004
    assert isinstance(density, Density)


def test_a_line_has_no_plane_in_any_unit():
    rng = np.random.default_rng(5)
    line = np.c_[rng.uniform(0, 1, 50), rng.normal(0, 1e-3, 50), rng.normal(0, 1e-3, 50)]
    disc = np.c_[rng.uniform(-1, 1, (50, 2)), rng.normal(0, 1e-3, 50)]
    for scale in (1e-3, 1.0, 1e3):
        assert fit_plane(line * scale) is None
        assert fit_plane(disc * scale) is not None


def test_a_cloud_outside_the_envelope_is_said_so(caplog):
    cloud, _, _ = candidate_flowers(60, seed=6)
    with caplog.at_level(logging.WARNING, logger="flowerpose"):
        find_flowers_in_candidates(Cloud(cloud.points * 5, cloud.colors))
    assert "outside the operating envelope" in caplog.text and "cm across" in caplog.text


def _one_thinned(points: int, seed: int, keep: float):
    """Candidate flowers with flower 2 keeping `keep` of its points (seen by fewer views)."""
    cloud, centres, normals = candidate_flowers(points, seed)
    near = np.linalg.norm(cloud.points - centres[2], axis=1) < 0.03
    dropped = near & (np.random.default_rng(seed).random(len(cloud)) > keep)
    return cloud.subset(np.flatnonzero(~dropped)), centres, normals


@pytest.mark.parametrize("seed", [0, 1])
def test_a_flower_sampled_sparser_than_its_neighbours_is_found(seed):
    # Its own spacing, not the other flowers', decides its coverage, within
    # sparse_flower_ratio, while it has the envelope's 50 points.
    sparse, centres, normals = _one_thinned(400, seed, 0.4)
    assert sorted(_matched(sparse, centres, normals)) == list(range(len(centres)))
    capped = apply_overrides(PipelineConfig(), {"cluster": {"sparse_flower_ratio": 1}})
    assert 2 not in _matched(sparse, centres, normals, capped)
    # Below the envelope, a few scattered points are held to the cloud's spacing.
    below, centres, normals = _one_thinned(200, 2, 0.3)
    assert 2 not in _matched(below, centres, normals)
