"""What an eval runs on and what it measures (a module of its own, so the command line
offers them without importing the harness)."""

#: Where the clouds come from: simulated scans reconstructed by photogrammetry, the
#: plant's surfaces sampled directly, a simulated depth camera's frames fused, or real
#: labelled plants (`real_source.py`).
SOURCES = ("scan", "oracle", "rgbd", "real")
#: ... those of synthetic plants, with exact truth.
SYNTHETIC_SOURCES = tuple(s for s in SOURCES if s != "real")

#: What an eval measures: the poses (Table I), or pollination visits with them as well.
TASKS = ("pose", "pollinate")
