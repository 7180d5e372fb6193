"""The dense stage's settings (`dense.reconstruct_dense`), checked when made."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2

from flowerpose.config import require


@dataclass(frozen=True)
class DenseConfig:
    """Dense reconstruction from posed frames (multi-view stereo on the CPU)."""

    # --- views and pairs ---
    max_view_angle_deg: float = 30.0
    """Two views can pair when their optical axes differ by at most this, degrees. The scan
    path's neighbours differ by 20 degrees (azimuth and dome steps)."""
    baseline_m: tuple[float, float] = (0.03, 0.2)
    """Camera-centre distance of a pair, metres (min, max). Shorter pairs triangulate poorly
    (2 cm at 0.5 m is 2 degrees); the scan path's horizontal neighbours are 0.17 m apart."""
    target_triangulation_deg: float = 14.0
    """A view's candidate partners are ranked by how close the angle between the two rays to
    the scene (at the view's expected depth) comes to this, degrees: a wider angle measures
    depth more finely, a narrower one makes the two images look more alike."""
    max_pairs_per_image: int = 4
    """Pairs each view asks for (it can take part in more: the pairs its neighbours chose).
    On the development scan 2, 3 and 4 gave 195, 294 and 344 pairs, 50, 61 and 77 s of
    matching on 2 cores, and plant F-scores at 5 mm of 0.87, 0.89 and 0.92 (more can rarely
    be had: the baselines must point 60 degrees apart)."""
    min_pair_direction_deg: float = 60.0
    """The baselines of one view's pairs must point at least this far apart in its image,
    degrees, so they match edges of different orientations (opposite directions count as
    different: they see round different sides of an occluder)."""
    min_epipole_angle_deg: float = 50.0
    """A pair is degenerate (skipped) when its baseline lies within this angle of either
    optical axis, degrees: the epipole then falls in or near the image and planar
    rectification stretches it without bound (forward motion)."""
    duplicate_distance_m: float = 0.005
    """Frames within this distance of a sharper frame, looking the same way (within
    `duplicate_angle_deg`), add nothing but time: they are dropped, metres."""
    duplicate_angle_deg: float = 2.0
    """The viewing directions of such duplicates differ by at most this, degrees."""
    # --- matching ---
    image_scale: float = 0.5
    """Images are resized by this before matching (1280 x 720 -> 640 x 360): SGM's time grows
    with the pixel count times the disparity range, so four times the pixels cost about
    eight times the time."""
    sgbm_mode: Literal["sgbm", "3way", "hh4", "hh"] = "3way"
    """cv2.StereoSGBM mode: "3way" (the fastest: half the time of "sgbm", as accurate on
    the development scan), "sgbm" (5 paths), "hh4", "hh" (full 8 paths, slow)."""
    block_size: int = 5
    """SGBM matching block side, pixels (odd)."""
    p1: int | None = None
    """SGBM penalty for a disparity change of 1 between neighbours; None: block_size^2.
    OpenCV suggests 8 and 32 block_size^2 for P1 and P2; the gentler 1 and 12 gave 14 %
    more pair depths within 5 mm of the truth on the development scan, and more of them
    right (the smooth petals and leaves are slanted, not fronto-parallel)."""
    p2: int | None = None
    """SGBM penalty for larger disparity changes; None: 12 * block_size^2."""
    uniqueness_ratio: int = 20
    """SGBM: the best cost must beat the second best by this percentage, else no match
    (OpenCV suggests 5-15; 20 took the share of pair depths within 5 mm of the truth from
    0.82 to 0.92 on the development scan, for 15 % fewer of them)."""
    speckle_window_px: int = 300
    """SGBM speckle filter: disparity blobs smaller than this (pixels) are removed (0: no
    filter). Small blobs are mostly mismatches on the smooth petals and in the sky."""
    speckle_range: int = 1
    """SGBM speckle filter: largest disparity step within one blob (OpenCV multiplies by 16)."""
    pre_filter_cap: int = 31
    """SGBM: clip of the x-derivative prefilter."""
    max_disparities: int = 256
    """Largest disparity search range of a pair, pixels (a multiple of 16); a pair that the
    depth range would give more loses the nearest depths."""
    min_texture: float = 2.5
    """Grey-level standard deviation (0-255) over a matching block that counts as texture;
    0: no texture mask."""
    texture_radius_px: float = 4.0
    """Pixels farther than this from any textured pixel are left unmatched (see
    `min_texture`): SGM would fill them with the disparity of what surrounds them, which
    puts the sky round every leaf's edge."""
    lr_max_diff_px: float = 1.0
    """Left-right check: a disparity is kept when the other image's disparity at its match
    differs by at most this, pixels."""
    # --- depth ---
    depth_range_m: tuple[float, float] = (0.08, 1.5)
    """Depths (along the optical axis) any view may see, metres (min, max)."""
    scene_radius_m: float | None = 0.3
    """The scene (the plant and the soil round it) lies within this distance of the scene
    centre, the point nearest all optical axes (the scan looks at the plant), metres: each
    view searches only depths within it of the centre's depth, and the cloud is cropped to
    this sphere (the bed and sky beyond are not the plant). The paper's plants, 0.3 m tall
    and 0.4 m wide, fit with a margin (the development plant reaches 0.24 m). None: no
    crop, `depth_range_m` alone."""
    scene_points_stretch: float | None = 0.25
    """Given the sparse model's points, each view searches only the depths where it sees
    them: their 1st to 99th percentile, widened by this fraction each way (COLMAP's rule for
    its own stereo) and kept within the ranges above. Stereo's time grows with the
    disparity range, which the nearest depth sets. None: the ranges above alone."""
    # --- fusion ---
    min_pair_support: int = 1
    """A view's pixel needs this many of its pairs' depth maps agreeing (within
    `depth_tolerance`) with their median."""
    background_window_px: int = 11
    """A matched pixel whose colour is nearer the mean colour of the unmatched pixels in
    this window round it than that of the matched ones is dropped (0: no such check). SGM
    smears a surface's disparity a few pixels onto a textureless background (the sky round
    every leaf seen from the side), and those pixels have the background's colour. On the
    development scan: sky-coloured points 4.4 % -> 2.5 %, petal precision at 2 mm 0.91 ->
    0.98, flowers the colour detector finds 7 -> 11 of 18."""
    fusion_neighbours: int = 16
    """Views a view's depths are checked against: the nearest in viewing direction among
    those within `fusion_max_angle_deg` and `fusion_max_distance_m` (16 rather than 10:
    plant F-score at 5 mm 0.92 -> 0.93, 2 s more)."""
    fusion_max_angle_deg: float = 45.0
    """Largest optical-axis difference of a view checked against, degrees."""
    fusion_max_distance_m: float = 0.4
    """Largest camera-centre distance of a view checked against, metres."""
    min_consistent_views: int = 2
    """A pixel becomes a point when at least this many other views agree with its depth."""
    depth_tolerance: float = 0.01
    """Relative depth difference under which two views agree (0.01: 5 mm at 0.5 m)."""
    max_free_space_violations: int | None = 0
    """After voxel down-sampling, a point is dropped when more than this many views (all of
    them are checked) see past it: their depth where it projects is larger by over
    `free_space_tolerance`, so it floats in empty space. This removes the fringe matching
    smears from every edge into a textureless background (the sky, a wall): views near the
    one that made it agree with it, but views from elsewhere see through it. On the
    development scan: sky-coloured points 10 % -> 0.8 %, petal precision at 2 mm 0.71 ->
    0.90. None: no check."""
    free_space_tolerance: float = 0.03
    """Relative depth excess that counts as seeing past a point (0.03: 15 mm at 0.5 m)."""
    free_space_window_px: int = 3
    """A view sees past a point only when its depths over this window (pixels, odd) round
    where the point lands all do: thin stems and edges survive a pixel's misalignment."""
    # --- cloud ---
    voxel_size_m: float = 0.001
    """Voxel down-sampling edge, metres (one point per voxel, its points' mean); 0: none.
    1 mm is the detect stage's grid pixel (`GridConfig.pixel_size_m`)."""
    brightest_view_colour: bool = True
    """A fused point takes the second-brightest colour among its own view and the views
    that agree on it: a well-lit look of the surface. Only 29 % of the petal pixels in the
    development scan's images are bright (value >= 0.70); the rest are petals seen edge-on
    or from their shaded side. Not the brightest: at an edge, one view a pixel off sees
    the bright sky past a dark leaf, and that sheen made leaves look like petals (seed 1 of
    the benchmark: plane errors of 39 and 50 degrees with the brightest, 5.9 at most with
    the second). False: the point's own view's colour."""
    voxel_colour_quantile: float | None = 0.75
    """A voxel's colour is that of its point at this brightness quantile (None: the mean
    colour). A petal's lit face and its shaded back (or its shaded look from the side)
    share voxels, and the mean greys white petals below what the colour detector takes for
    white; the brightest point (1.0) would let one sky-coloured point from an edge colour a
    dark stem's voxel; 0.75 keeps the well-lit look of most voxels."""
    outlier_neighbours: int = 20
    """Statistical outlier removal: neighbours averaged (0: no removal)."""
    outlier_std_ratio: float = 2.0
    """Statistical outlier removal: points farther than the mean neighbour distance plus this
    many standard deviations are removed."""
    threads: int = 0
    """Worker threads for the pairs; 0: one per CPU core."""

    def __post_init__(self):
        checks = [
            (0 < self.image_scale <= 1, "image_scale", "must be in (0, 1]"),
            (self.block_size >= 1 and self.block_size % 2 == 1, "block_size",
             "must be a positive odd number"),
            (self.max_disparities >= 16 and self.max_disparities % 16 == 0, "max_disparities",
             "must be a positive multiple of 16"),
            (0 <= self.baseline_m[0] < self.baseline_m[1], "baseline_m", "needs 0 <= min < max"),
            (0 < self.depth_range_m[0] < self.depth_range_m[1], "depth_range_m",
             "needs 0 < min < max"),
            (self.max_pairs_per_image >= 1, "max_pairs_per_image", "must be at least 1"),
            (self.min_pair_support >= 1, "min_pair_support", "must be at least 1"),
            (self.min_consistent_views >= 0, "min_consistent_views", "must be 0 or more"),
            (self.fusion_neighbours >= 1, "fusion_neighbours", "must be at least 1"),
            (self.depth_tolerance > 0, "depth_tolerance", "must be positive"),
            (self.lr_max_diff_px >= 0, "lr_max_diff_px", "must be 0 or more"),
            (self.free_space_tolerance > 0, "free_space_tolerance", "must be positive"),
            (self.free_space_window_px >= 1 and self.free_space_window_px % 2 == 1,
             "free_space_window_px", "must be a positive odd number"),
            (self.scene_radius_m is None or self.scene_radius_m > 0, "scene_radius_m",
             "must be positive (metres) or unset"),
            (self.voxel_size_m >= 0, "voxel_size_m", "must be 0 or more (metres)"),
            (self.voxel_colour_quantile is None or 0 <= self.voxel_colour_quantile <= 1,
             "voxel_colour_quantile", "must be within 0-1 or unset"),
            (self.threads >= 0, "threads", "must be 0 (every core) or more"),
            (self.scene_points_stretch is None or 0 <= self.scene_points_stretch < 1,
             "scene_points_stretch", "must be within 0-1 or unset"),
            (self.sgbm_mode in SGBM_MODES, "sgbm_mode", f"one of {', '.join(SGBM_MODES)}"),
        ]
        for ok, key, problem in checks:
            require(ok, f"dense.{key}", problem)


SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
               "hh4": cv2.STEREO_SGBM_MODE_HH4, "hh": cv2.STEREO_SGBM_MODE_HH}
