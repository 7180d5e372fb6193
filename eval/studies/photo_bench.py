"""Real photographs to a cloud, timed and checked (`flowerpose bench --photos SET_DIR`).

A photo set laid out as `flowerpose data fetch romi-arabidopsis` makes it (images/, the
calibrated cameras as a COLMAP model in colmap/, the logged rough poses in poses.csv or the
scanner's metadata/ they are made from; millimetres) is taken in and reconstructed three
ways: with the calibrated model, with the rough poses only, and from the images alone. Each
is timed (frames, sparse, dense) and its camera centres compared with the calibrated ones
(as placed where poses were given; after a similarity where none were), and the three
clouds with each other: F-score at 2 and 5 mm as the cameras' similarity places them, and
after a rigid ICP from there (the standard last step of comparing two reconstructions;
no scale, so a cloud's size is still the cameras').
"""

from __future__ import annotations

# cv2 before pycolmap (pipeline/sfm.py says why).
import cv2  # noqa: F401  # isort: skip

import os
from pathlib import Path

import numpy as np

from flowerpose.cloudio import read_cloud
from flowerpose.errors import InputError
from flowerpose.eval.capture.quality import cloud_agreement, rigid_icp
from flowerpose.eval.reports.report import markdown_table, run_record
from flowerpose.jsonio import write_json
from flowerpose.log import LOG
from flowerpose.pipeline.align import Similarity, umeyama
from flowerpose.pipeline.photos import PhotoImportConfig, import_photos, read_colmap_model
from flowerpose.pipeline.reconstruct import ReconstructConfig, reconstruct
from flowerpose.stopwatch import Stopwatch

#: The ways the set is taken in: what `frames --images` is given besides the photos.
WAYS = ("calibrated", "rough", "none")
#: F-score thresholds between the three clouds, metres.
AGREEMENT_M = (0.002, 0.005)


def _set_files(set_dir: Path, work: Path) -> tuple[Path, Path, Path]:
    """(images/, colmap/, poses.csv) of a photo set; poses.csv made from metadata/ when
    the set has only the scanner's own files."""
    from flowerpose.data import romi_rough_poses

    images, colmap, poses = set_dir / "images", set_dir / "colmap", set_dir / "poses.csv"
    for needed in (images, colmap):
        if not needed.is_dir():
            raise InputError(needed, "not found: a photo set holds images/ and colmap/ (as "
                             "flowerpose data fetch romi-arabidopsis lays it out)")
    if not poses.is_file():
        work.mkdir(parents=True, exist_ok=True)
        poses = romi_rough_poses(set_dir / "metadata", work / "poses.csv")
    return images, colmap, poses


def _compared(found: dict[str, np.ndarray], calibrated: dict[str, np.ndarray]
              ) -> tuple[dict, Similarity]:
    """Camera centres (metres) against the calibrated ones: RMS as placed, and after the
    best similarity, with its scale."""
    names = sorted(set(found) & set(calibrated))
    a = np.array([found[n] for n in names])
    b = np.array([calibrated[n] for n in names])
    similarity = umeyama(a, b)
    rms = float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))
    aligned = float(np.sqrt(np.mean(np.sum((similarity.apply(a) - b) ** 2, axis=1))))
    up = similarity.rotation @ np.array([0.0, 0.0, 1.0])
    return {"compared": len(names), "centres_rms_mm": round(1000 * rms, 3),
            "centres_rms_after_similarity_mm": round(1000 * aligned, 3),
            "similarity_scale": round(similarity.scale, 5),
            "up_error_deg": round(float(np.degrees(np.arccos(np.clip(up[2], -1, 1)))), 3)
            }, similarity


def run_photo_bench(set_dir: Path, out: Path, max_size: int | None = None,
                    config: ReconstructConfig | None = None, overwrite: bool = False) -> dict:
    """Take the set in and reconstruct it the three ways into out/WAY/; write
    out/photo_bench.json and print its table. Returns the report."""
    set_dir, out = Path(set_dir), Path(out)
    config = config or ReconstructConfig()
    images, colmap, poses = _set_files(set_dir, out)
    calibrated = {name: pose.position for name, pose in
                  read_colmap_model(colmap, "mm")[1].items()}
    given = {"calibrated": {"colmap": colmap}, "rough": {"poses": poses}, "none": {}}
    ways, clouds = {}, {}
    for way in WAYS:
        LOG.info(f"photo bench: {way} poses")
        watch = Stopwatch()
        with watch.step("frames"):
            frames = import_photos(images, out / way / "frames",
                                   PhotoImportConfig(max_size=max_size, units="mm"),
                                   overwrite=overwrite, **given[way])
        with watch.step("reconstruct"):
            result = reconstruct(out / way / "frames", out / way / "recon", config,
                                 progress=False, overwrite=overwrite)
        found = {image.name.split("/")[-1]: image.projection_center()
                 for image in result.sparse.reconstruction.images.values()
                 if image.has_pose and image.num_points3D >= 30}
        comparison, similarity = _compared(found, calibrated)
        clouds[way] = similarity.apply(read_cloud(result.report["cloud"], units="m").points)
        seconds = watch.report(digits=3)
        ways[way] = {"images": len(frames["frames"]),
                     "registered": result.report["images_registered"],
                     "mode": result.report["sparse"]["mode"],
                     "camera": result.report["sparse"]["camera"],
                     "metric": result.report["metric"], "points": result.report["points"],
                     **comparison,
                     "seconds": {"frames": seconds["frames"],
                                 **{f"sparse_{k}": v for k, v in
                                    result.report["sparse"]["seconds"].items() if k != "total"},
                                 "dense": result.report["seconds"]["dense"],
                                 "total": seconds["total"]}}
    agreement = {}
    for i, a in enumerate(WAYS):
        for b in WAYS[i + 1:]:
            refined = rigid_icp(clouds[a], clouds[b])
            agreement[f"{a}-{b}"] = {
                **{f"placed {1000 * t:g}mm": round(cloud_agreement(
                    clouds[a], clouds[b], t)["fscore"], 4) for t in AGREEMENT_M},
                **{f"after ICP {1000 * t:g}mm": round(cloud_agreement(
                    refined, clouds[b], t)["fscore"], 4) for t in AGREEMENT_M}}
    report = {"run": run_record(), "set": str(set_dir), "max_size": max_size,
              "cpu_count": os.cpu_count(), "ways": ways, "agreement": agreement}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "photo_bench.json", report)
    print(photo_bench_markdown(report), end="")
    print(f"photo bench: {out / 'photo_bench.json'}")
    return report


def photo_bench_markdown(report: dict) -> str:
    """photo_bench.json as Markdown: a row per way, then the clouds' agreement."""
    rows = []
    for way, r in report["ways"].items():
        centres = (f"{r['centres_rms_mm']:.2f}" if way != "none"
                   else f"{r['centres_rms_after_similarity_mm']:.2f} (after a similarity)")
        rows.append([way, f"{r['registered']} of {r['images']}", centres,
                     f"{r['similarity_scale']:.4f}", f"{r['up_error_deg']:.2f}",
                     f"{r['points']:,}", f"{r['seconds']['total']:.1f}"])
    table = markdown_table(["poses", "registered", "camera centres vs calibrated, mm RMS",
                            "scale vs calibrated", "up error, °", "cloud points", "seconds"],
                           rows)
    agreement = markdown_table(["clouds", *report["agreement"][next(iter(
        report["agreement"]))]], [[pair, *(f"{v:.3f}" for v in scores.values())]
                                  for pair, scores in report["agreement"].items()])
    size = f"at most {report['max_size']} px" if report["max_size"] else "full size"
    return (f"{table}\n\nphotos {size}, {report['cpu_count']} cores\n\nF-score between the "
            f"clouds, as the cameras place them and after a rigid ICP\n\n{agreement}\n")
