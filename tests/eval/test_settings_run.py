"""report.json's config holds the settings of the stages that ran, and no others."""

import pytest

from flowerpose.eval.jobs.config import EvalConfig, settings_run

PIPELINE = ["colour", "ground", "grid", "detect", "outliers", "cluster", "pose"]


@pytest.mark.parametrize("source, starts, sections", [
    ("oracle", ["cloud"], PIPELINE + ["sim", "score"]),
    ("scan", ["cloud"], PIPELINE + ["sim", "score", "scan"]),
    ("rgbd", ["cloud"], PIPELINE + ["sim", "score", "rgbd", "fusion"]),
    ("real", ["candidates"], ["colour", "outliers", "cluster", "pose", "score"]),
    ("real", ["crops"], ["colour", "cluster", "pose", "score"]),
    # Folders of several kinds: the union of what ran, in the config's order.
    ("real", ["crops", "cloud"], PIPELINE + ["score"]),
])
def test_each_source_and_start_records_the_sections_it_read(source, starts, sections):
    config = EvalConfig()
    recorded = settings_run(config, source, starts)
    assert list(recorded) == sections
    assert recorded["cluster"]["eps"] == config.cluster.eps
