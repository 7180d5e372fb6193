"""The operating envelope: the clouds the pipeline is built and tested for, and what a run
says of a cloud outside it (DESIGN.md, "The operating envelope").

Within the envelope every limit of the pipeline holds (`limits` sizes those stated in
metres and in points to the cloud); `flowerpose stress` measures how results change across
it and beyond. Outside it the pipeline still runs, and says which bound the cloud crosses,
as measured on the flowers it found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Points a flower's crop holds: from a coarse or fast scan to a dense reconstruction. The
#: upper bound covers what the simulated FarmBot's own default scan reconstructs (1,800 to
#: 2,600 a flower on seeds 100-105, 72 of 73 visible flowers found) and oracle clouds of
#: 4,100 to 6,500 a flower (seeds 300-305: 82 of 83 found, plane 1.71 degrees; 83 and 1.80
#: at the default 150-300): above the reference density the grouping thins the candidates.
POINTS_PER_FLOWER = (50, 5000)
#: Flower diameters, metres (a strawberry flower: 2-6 cm across).
FLOWER_DIAMETER_M = (0.02, 0.06)
#: A measured size says the cloud crosses a bound only beyond this factor of it: twice a
#: corolla's measured radius runs up to a tenth over the petal tips' span.
SIZE_TOLERANCE = 1.25
#: Largest colour cast, the relative change of one channel's linear light.
MAX_CAST = 0.15
#: Exposure, a factor on linear light, and Gaussian position noise, metres: within these
#: the stress report holds recall (no run measures them on a cloud of unknown truth).
EXPOSURE = (0.6, 1.3)
MAX_NOISE_M = 0.0015


@dataclass(frozen=True)
class CloudMeasure:
    """What a detection measured of its cloud, in the cloud's unit."""

    points_per_flower: float | None
    """The median points of the flowers' crops (None: no flower)."""
    flower_diameter: float | None
    """Twice the typical flower radius (`segment.typical_radius`; None: no flower)."""
    white_gain: tuple[float, float, float]
    """The white balance's gain per channel (`colour.white_gain`): 1 for no cast."""

    def outside(self, metric: bool) -> list[str]:
        """A line for each bound of the envelope the cloud crosses; `metric`: the cloud is
        known to be in metres (its diameters are then checked too)."""
        lines = []
        low, high = POINTS_PER_FLOWER
        if self.points_per_flower is not None and not low <= self.points_per_flower <= high:
            lines.append(f"its flowers hold {self.points_per_flower:.0f} points each "
                         f"(median), outside the {low}-{high} the pipeline is built for")
        low, high = FLOWER_DIAMETER_M
        if metric and self.flower_diameter is not None and not (
                low / SIZE_TOLERANCE <= self.flower_diameter <= high * SIZE_TOLERANCE):
            lines.append(f"its flowers measure {100 * self.flower_diameter:.1f} cm across, "
                         f"outside {100 * low:g}-{100 * high:g} cm: is the cloud in metres "
                         "(--units)?")
        gain = np.asarray(self.white_gain)
        cast = float(np.max(np.abs(1.0 / gain - 1.0)))
        if cast > MAX_CAST:
            channel = "rgb"[int(np.argmax(np.abs(1.0 / gain - 1.0)))]
            lines.append(f"a colour cast of {100 * cast:.0f}% in {channel} was removed, "
                         f"beyond the {100 * MAX_CAST:g}% the colour tests are checked for")
        return lines

    def to_json(self) -> dict:
        return {"points_per_flower": self.points_per_flower,
                "flower_diameter": self.flower_diameter,
                "white_gain": [round(float(g), 4) for g in self.white_gain]}
