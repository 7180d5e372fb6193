"""The renderer's light and surroundings, apart from the renderer so that configs can name
them without loading OpenGL."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RenderConfig:
    """Lighting and surroundings of the plant renderer. Light levels are shares of a
    surface's own colour it shows under that light alone (so the defaults add up to
    about 1 on a surface facing the sun under open sky: white petals stay just below
    clipping, as with a well-set fixed exposure)."""

    sun_elevation_deg: float = 55.0
    """Sun elevation above the horizon, degrees."""
    sun_azimuth_deg: float = 135.0
    """Sun azimuth in the bed frame, degrees counter-clockwise from +x (toward +y)."""
    sun: float = 0.68
    """Sun light on a surface facing it."""
    sun_softness_deg: float = 2.0
    """Half-angle of the cone the sun's shadow rays spread over, degrees (soft shadow
    edges: the sun's disc and haze)."""
    fill: float = 0.1
    """Fill light (sky and walls opposite the sun) on a surface facing it; it comes
    from the azimuth opposite the sun at `fill_elevation_deg`, shadowed too."""
    fill_elevation_deg: float = 30.0
    """Elevation of the fill light, degrees."""
    sky: float = 0.3
    """Sky light on a surface that sees the whole sky (an open, upward surface); less
    where plants hide part of it or it lies below the surface's own horizon."""
    bounce: float = 0.08
    """Light a surface gets from the part of its view that is not sky (ground, leaves)."""
    sky_tint: tuple[float, float, float] = (0.93, 1.0, 1.12)
    """Colour of the sky and fill light, linear RGB factors (a slightly blue sky: shaded
    white petals turn faintly blue-grey, as in photographs)."""
    sky_rays: int = 16
    """Rays per vertex and side that measure how much sky it sees."""
    shadows: bool = True
    """Shadows and sky occlusion by ray casting; False: every surface sees its lights and
    the half of the sky above its horizon (faster to build, flatter to look at)."""
    smooth: bool = True
    """Light each vertex and interpolate (curved petals and leaves shade smoothly); False
    lights each triangle as a whole (faceted)."""
    background_rgb: tuple[int, int, int] = (150, 160, 170)
    """Colour where no surface is seen (beyond the ground), RGB 0-255."""
    ground_margin_m: float | None = 1.0
    """A flat soil ground reaching this far beyond the plants' extent on every side,
    metres; None: no ground, only the plants' soil discs."""
    ground_z_m: float | None = None
    """Height of the ground surface, metres; None: 1 mm below the lowest point of the
    plants' soil discs, so the discs (z = 0 on average) cover it wholly and stand on it
    like low mounds."""
