"""The gallery's pictures and the sample outputs, from the runs scripts/gallery.sh made.

usage: python scripts/gallery.py RUNS IMAGES SAMPLES

- report.png: the top of an eval's report.html (Table I, intervals) and report-3d.png its
  3D view of a plant, screenshots from headless Chromium (Playwright, the system browser);
- views.png: detect's grid views with their detections;
- stress.png: the stress report's curves; pollination.png: the pollination plot;
- filming.png: MuJoCo's view of the simulated FarmBot filming (a frame of preview.mp4) beside
  a frame the simulated camera recorded;
- photos-cloud.png: the shared real photos' cloud from the images alone, with the cameras,
  seen from the side and from above;
- SAMPLES/flowers.json, SAMPLES/report.json, SAMPLES/report.md: what detect and score write
  (report.md's headings two levels down, for the page it goes into).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

#: Widest picture in the docs, pixels (the page's text column is narrower; a click shows it
#: whole).
MAX_WIDTH = 1400


def _fit(image: np.ndarray) -> np.ndarray:
    height, width = image.shape[:2]
    if width <= MAX_WIDTH:
        return image
    return cv2.resize(image, (MAX_WIDTH, round(height * MAX_WIDTH / width)),
                      interpolation=cv2.INTER_AREA)


def _copy_image(source: Path, target: Path) -> None:
    image = cv2.imread(str(source), cv2.IMREAD_COLOR)
    if image is None:
        raise SystemExit(f"gallery: {source}: missing or not an image")
    cv2.imwrite(str(target), _fit(image))


def _screenshots(report: Path, images: Path) -> None:
    """The report's tables and its first 3D view, in the system Chromium."""
    from playwright.sync_api import sync_playwright

    browser_path = shutil.which("chromium") or shutil.which("chromium-browser")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=browser_path, args=[
            "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"])
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(report.resolve().as_uri())
        page.wait_for_selector(".plotly .main-svg")
        page.screenshot(path=str(images / "report.png"))
        view = page.locator(".js-plotly-plot").last
        view.scroll_into_view_if_needed()
        page.wait_for_timeout(1500)  # WebGL draws after the scroll
        view.screenshot(path=str(images / "report-3d.png"))
        browser.close()


def _filming(scan: Path, images: Path) -> None:
    """A frame of MuJoCo's preview beside a frame the simulated camera took."""
    video = cv2.VideoCapture(str(scan / "preview.mp4"))
    count = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
    video.set(cv2.CAP_PROP_POS_FRAMES, count // 3)
    ok, outside = video.read()
    video.release()
    if not ok:
        raise SystemExit(f"gallery: {scan / 'preview.mp4'}: no frame to read")
    frames = sorted((scan / "frames").glob("*.jpg")) + sorted((scan / "frames").glob("*.png"))
    if not frames:
        raise SystemExit(f"gallery: {scan / 'frames'}: no recorded frame")
    inside = cv2.imread(str(frames[len(frames) // 2]), cv2.IMREAD_COLOR)
    inside = cv2.resize(inside, (round(inside.shape[1] * outside.shape[0] / inside.shape[0]),
                                 outside.shape[0]), interpolation=cv2.INTER_AREA)
    gap = np.full((outside.shape[0], 8, 3), 255, np.uint8)
    cv2.imwrite(str(images / "filming.png"), _fit(np.hstack([outside, gap, inside])))


def photos_cloud(recon: Path, target: Path) -> None:
    """A reconstruction's cloud (a sample of its points, their own colours) and its
    registered cameras (centres and optical axes), from the side and from above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flowerpose.atomic import write_figure
    from flowerpose.cloudio import read_cloud
    from flowerpose.jsonio import read_json

    cloud = read_cloud(recon / "cloud.ply", units="m")
    keep = np.random.default_rng(0).permutation(len(cloud))[:20000]
    points, colours = cloud.points[keep], cloud.colors[keep] / 255.0
    import pycolmap

    images = [image for image in pycolmap.Reconstruction(str(recon / "sparse")).images.values()
              if image.has_pose]
    centres = np.array([image.projection_center() for image in images])
    axes = np.array([image.cam_from_world().rotation.matrix()[2] for image in images])
    metric = read_json(recon / "reconstruction.json").get("metric", True)
    figure, panels = plt.subplots(1, 2, figsize=(12, 6))
    for panel, (a, b), title in ((panels[0], (0, 2), "side (x, z)"),
                                 (panels[1], (0, 1), "above (x, y)")):
        panel.scatter(points[:, a], points[:, b], c=colours, s=0.5, linewidths=0)
        panel.scatter(centres[:, a], centres[:, b], c="tab:red", s=12, label="cameras")
        panel.quiver(centres[:, a], centres[:, b], axes[:, a], axes[:, b], color="tab:red",
                     width=0.003, scale=12)
        panel.set_aspect("equal")
        panel.set_title(title)
        panel.set_xlabel("metres" if metric else "metres, at an assumed camera distance")
    panels[0].legend(loc="upper right")
    figure.suptitle(f"{len(cloud):,} points from {len(images)} photographs")
    figure.tight_layout()
    write_figure(target, figure, dpi=110)
    plt.close(figure)


def main(runs: Path, images: Path, samples: Path) -> None:
    _copy_image(runs / "detect3" / "views" / "views.png", images / "views.png")
    _copy_image(runs / "stress2" / "stress.png", images / "stress.png")
    _copy_image(runs / "eval2" / "pollination.png", images / "pollination.png")
    _filming(runs / "scan3", images)
    photos_cloud(runs / "photos" / "recon", images / "photos-cloud.png")
    _screenshots(runs / "eval2" / "report.html", images)
    shutil.copyfile(runs / "detect3" / "flowers.json", samples / "flowers.json")
    shutil.copyfile(runs / "score3" / "report.json", samples / "report.json")
    # report.md goes into a page under its own headings: its headings two levels down.
    lines = (runs / "score3" / "report.md").read_text(encoding="utf-8").splitlines()
    (samples / "report.md").write_text("\n".join("##" + line if line.startswith("#") else line
                                                 for line in lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__.split("\n\n")[1])
    main(*(Path(a) for a in sys.argv[1:]))
