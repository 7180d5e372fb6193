from dataclasses import dataclass, field
from typing import Literal

import pytest

from flowerpose.config import apply_overrides, load_toml, parse_set_options, to_dict
from flowerpose.errors import InputError


@dataclass(frozen=True)
class Inner:
    eps: float = 0.01
    """doc"""
    mode: Literal["mask", "box"] = "mask"
    range_: tuple[float, float] = (1.0, 2.0)
    flag: bool = False


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    count: int = 3


def test_dotted_overrides_coerce_to_field_types():
    config = apply_overrides(Outer(), parse_set_options(
        ["inner.eps=0.008", "inner.mode=box", "count=5", "inner.flag=true",
         "inner.range_=(0.5, 3)"]))
    assert config.inner == Inner(0.008, "box", (0.5, 3.0), True)
    assert config.count == 5
    assert Outer().inner.eps == 0.01  # the original is untouched


def test_nested_dicts_from_toml(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("count = 7\n[inner]\neps = 0.02\n")
    config = apply_overrides(Outer(), load_toml(path))
    assert (config.count, config.inner.eps) == (7, 0.02)
    assert to_dict(config) == {"inner": {"eps": 0.02, "mode": "mask", "range_": [1.0, 2.0],
                                         "flag": False}, "count": 7}


def test_stage_configs_refuse_values_outside_their_range():
    from flowerpose.pipeline.flowers import PipelineConfig

    for item in ("grid.pixel_size_m=0", "grid.splat_radius_px=-1", "cluster.eps=0",
                 "cluster.min_points=-5", "outliers.radius_m=-1", "pose.max_fit_points=-1",
                 "detect.min_area_m2=1", "colour.pistil_hue=(70, 40)", "ground.sample_points=0"):
        with pytest.raises(InputError, match=item.split("=")[0].split(".")[0]):
            apply_overrides(PipelineConfig(), parse_set_options([item]))


@pytest.mark.parametrize("item, match", [
    ("inner.epss=1", "inner.epss"), ("count=abc", "count"), ("inner.mode=circle", "inner.mode"),
    ("inner=3", "inner"), ("inner.eps=nan", "inner.eps"), ("noequals", "^set: expected key=value"),
    ("count=2.5", "whole number"), ("count=true", "whole number"),
    ("inner.range_=(1, 2, 3)", "expected 2 values")])
def test_bad_overrides_name_the_key(item, match):
    with pytest.raises(InputError, match=match):
        apply_overrides(Outer(), parse_set_options([item]))


def test_bad_toml_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("count = = 3")
    with pytest.raises(InputError, match="bad.toml"):
        load_toml(path)
    with pytest.raises(InputError, match="not found"):
        load_toml(tmp_path / "missing.toml")


def test_the_upstream_profile_loads_and_sets_what_it_says():
    from flowerpose.config import load_profile, profile_names
    from flowerpose.pipeline.flowers import PipelineConfig

    assert "upstream" in profile_names()
    settings = load_profile("upstream")
    config = apply_overrides(PipelineConfig(), settings)
    changed = 0
    for section, values in settings.items():
        for key, value in values.items():
            got = getattr(getattr(config, section), key)
            expected = None if value == "none" else tuple(value) if isinstance(value, list) \
                else value
            assert got == expected, f"{section}.{key}"
            changed += got != getattr(getattr(PipelineConfig(), section), key)
    assert changed >= 20  # the profile is mostly deviations, not the defaults restated
    assert config.pose.direction_reference == "crop" and config.detect.backproject == "box"


def test_an_unknown_profile_is_refused():
    from flowerpose.config import load_profile

    with pytest.raises(InputError, match="no profile 'nope'"):
        load_profile("nope")


@dataclass(frozen=True)
class _Inner:
    width_m: float = 0.5
    """How wide, metres."""
    undocumented: int = 1


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    """A section."""
    count: int = 3
    """How many: a docstring
    over two lines."""


def test_a_settings_docstring_is_read_from_its_dataclass():
    from flowerpose.config import setting_doc

    assert setting_doc(_Outer(), "count") == "How many: a docstring over two lines."
    assert setting_doc(_Outer(), "inner.width_m") == "How wide, metres."
    assert setting_doc(_Outer(), "inner") == "A section."
    assert setting_doc(_Outer(), "inner.undocumented") == ""
