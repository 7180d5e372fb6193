"""Real data fetched for the user: the authors' published files of a plant, laid out as a
real plant folder (DESIGN.md, "A real labelled plant") with the project's own source.json
and the authors' licence beside them; and real photographs of a plant (the ROMI scanner's,
for `frames --images`), with the files derived from their metadata that the guide uses.
Each is pinned to one commit of its repository, every file checked by SHA-256.

A fetch downloads into a private folder beside the target and renames it into place only
when every file is there and matches its checksum, so a failed or interrupted fetch leaves
nothing half-written that a later run would trust. `mirror` (a folder laid out as the
authors' repository, or a URL prefix) stands in for GitHub: the tests use one, and so can a
lab without internet access.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from flowerpose.errors import InputError
from flowerpose.jsonio import write_json

#: The authors' repository and the commit its files are pinned to.
REPOSITORY = "harshmuriki/flowerPose"
COMMIT = "8c430b3"
UPSTREAM = f"https://raw.githubusercontent.com/{REPOSITORY}/{COMMIT}/"
#: Seconds a download may stall before it is given up.
TIMEOUT_S = 60.0


@dataclass(frozen=True)
class PublishedFile:
    """One file of a plant: where it lies in the authors' repository, where it goes in the
    plant folder, and its SHA-256."""

    upstream: str
    local: str
    sha256: str


@dataclass(frozen=True)
class PublishedPlant:
    """A published data set: a plant whose labels and candidate clouds are complete, or a
    plant's photographs."""

    name: str
    description: str
    files: tuple[PublishedFile, ...]
    source: dict = field(default_factory=dict)
    """The project's source.json for it: what the published files do not carry."""
    repository: str = REPOSITORY
    """The GitHub repository, owner/name."""
    commit: str = COMMIT
    """The commit its files are pinned to."""

    @property
    def upstream(self) -> str:
        """The URL prefix of its files."""
        return f"https://raw.githubusercontent.com/{self.repository}/{self.commit}/"


_CANDIDATES = {0: "ad135fb36721c08f5c9e71427afb642c0857c978b2de20d5136092fc50587f39",
               1: "c9ce5a29b9eded706df2e2ebc5458607dce0ede62c6cc63e149f1282f478a448",
               3: "9bb2a4c247f95d82595deb3428687f6a1376e27832e661e2ecb2a6b4254404cd",
               4: "8114e37b88f1a4ad458425b66c042739e092ae91a2290c71643df048bf873d69",
               5: "9f74d2e32ec6daf31e1a14d7c2582c6065c3dcb8620d0cd0e80a34cc2d7f0610"}

#: The plants `data fetch` knows. The authors' repository numbers its scans 4-11 as the
#: paper's 1-8 (its FinalDatasets/OldData - NewData.txt): its Data6 is the paper's plant 3,
#: the one scan whose detector candidates it also publishes (deeplearning/paper/pcd_*.ply;
#: pcd_2 was never published). The whole clouds are not in the repository.
PLANTS: dict[str, PublishedPlant] = {
    "paper-plant-3": PublishedPlant(
        "paper-plant-3",
        "the paper's plant 3 (the authors' Data6): 11 labelled flowers, the candidate points "
        "of five of the six grid views",
        (PublishedFile("FinalDatasets/Data6/output6.json", "labels.json",
                       "d1bef228331f5fa4d2511e0bab7759542ed26f8407b9a28586eb5515657d702a"),
         *(PublishedFile(f"deeplearning/paper/pcd_{k}.ply", f"candidates/pcd_{k}.ply", digest)
           for k, digest in _CANDIDATES.items()),
         PublishedFile("LICENSE", "LICENSE-flowerPose.txt",
                       "229af356d08c68b2922e43709d1bf3df3241bf43af538a330c18bf82ebc5a12b")),
        {"truth_scale": 25,
         "note": "the paper's plant 3 (the authors' Data6), fetched by flowerpose data fetch "
                 f"from github.com/{REPOSITORY} at {COMMIT}; two open flowers in the cloud "
                 "carry no label: their centres, in label units, are listed as unlabelled",
         "unlabelled": [[-2.838, -0.507, 10.838], [-3.01, 5.514, 11.608]]}),
}

def _photo_set(name: str, description: str) -> PublishedPlant:
    """A photo set listed in assets/data/NAME.json (its repository, commit and files)."""
    from importlib import resources

    from flowerpose.jsonio import read_json

    with resources.as_file(resources.files("flowerpose.assets") / "data" / f"{name}.json") \
            as path:
        manifest = read_json(path)
    files = tuple(PublishedFile(f["upstream"], f["local"], f["sha256"])
                  for f in manifest["files"])
    source = {"note": f"{description}; fetched by flowerpose data fetch from "
                      f"github.com/{manifest['repository']} at {manifest['commit']}",
              "licence": "GNU LGPL 3.0 (LICENSE)"}
    return PublishedPlant(name, description, files, source, manifest["repository"],
                          manifest["commit"])


PLANTS["romi-arabidopsis"] = _photo_set(
    "romi-arabidopsis",
    "60 real photographs of a potted Arabidopsis round a 300 mm circle by the ROMI scanner, "
    "with its logged poses (poses.csv, millimetres) and calibrated cameras (colmap/, "
    "millimetres)")

#: Where a mirror of the authors' repository is, when none is given on the command line.
MIRROR_ENV = "FLOWERPOSE_DATA_MIRROR"


def default_data_dir() -> Path:
    """Where fetched plants go: $XDG_CACHE_HOME/flowerpose-data (~/.cache by default)."""
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "flowerpose-data"


def plant(name: str) -> PublishedPlant:
    if name not in PLANTS:
        raise InputError(name, f"no published plant of that name (known: {', '.join(PLANTS)})")
    return PLANTS[name]


def fetch(name: str, to: Path | None = None, mirror: str | None = None) -> tuple[Path, list]:
    """Fetch plant `name` into `to` (default: `default_data_dir()`/NAME) from the authors'
    repository or `mirror`; returns the folder and, per file, (path, bytes, sha256). A
    folder already holding the plant, whole, is checked and kept."""
    published = plant(name)
    folder = Path(to) if to is not None else default_data_dir() / name
    mirror = mirror if mirror is not None else os.environ.get(MIRROR_ENV)
    if folder.exists():
        return folder, _verified(published, folder, fetched=False)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        for item in published.files:
            target = staging / item.local
            target.parent.mkdir(parents=True, exist_ok=True)
            _download(item, target, mirror, published.upstream)
        write_json(staging / "source.json", published.source)
        found = _verified(published, staging)
        if (staging / "metadata").is_dir():
            _derive_romi(staging)
        os.replace(staging, folder)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return folder, [(folder / p.relative_to(staging), n, d) for p, n, d in found]


def _download(item: PublishedFile, target: Path, mirror: str | None,
              upstream: str = UPSTREAM) -> None:
    base = upstream if mirror is None else mirror
    if mirror is not None and "://" not in mirror:
        source = Path(mirror) / item.upstream
        if not source.is_file():
            raise InputError(source, f"not in the mirror (the plant's {item.local})")
        shutil.copyfile(source, target)
        return
    url = base.rstrip("/") + "/" + item.upstream
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response, \
                open(target, "wb") as out:
            shutil.copyfileobj(response, out)
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", None) or getattr(err, "strerror", None) or err
        raise InputError(url, f"download failed ({reason}); nothing was kept") from None


def _verified(published: PublishedPlant, folder: Path,
              fetched: bool = True) -> list[tuple[Path, int, str]]:
    """Each file's (path, bytes, sha256), checked against the published digests (`fetched`:
    just downloaded, so a bad one means nothing is kept; else a folder fetched before)."""
    found = []
    for item in published.files:
        path = folder / item.local
        if not path.is_file():
            raise InputError(path, f"missing: {folder} is not a whole fetch of "
                             f"{published.name}; remove it and fetch again")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != item.sha256:
            after = ("nothing was kept" if fetched else
                     f"remove {folder} and fetch again")
            raise InputError(path, f"does not match its published checksum (sha256 "
                             f"{digest[:12]}..., expected {item.sha256[:12]}...); {after}")
        found.append((path, path.stat().st_size, digest))
    return found


#: The ROMI scanner logs its gimbal's pan with 0 pointing the camera along -y; the rough
#: poses' heading (`pipeline.photos.read_pose_table`) is measured from +x: 90 degrees on.
ROMI_PAN_TO_HEADING_DEG = 90.0


def _derive_romi(folder: Path) -> None:
    """A ROMI photo set's derived files: poses.csv (the logged poses) and colmap/ (the
    calibrated cameras as a COLMAP text model, millimetres, z up)."""
    romi_rough_poses(folder / "metadata", folder / "poses.csv")
    romi_colmap_model(folder / "metadata", folder / "colmap")


def romi_colmap_model(metadata_dir: Path, out_dir: Path) -> Path:
    """The calibrated cameras of a ROMI scan's metadata ("colmap_camera": OPENCV camera,
    world-to-camera rotmat and tvec, millimetres) as a COLMAP text model in out_dir."""
    import numpy as np

    from flowerpose.atomic import write_text
    from flowerpose.jsonio import read_json
    from flowerpose.scanio import matrix_to_quaternion

    files = sorted(Path(metadata_dir).glob("*.json"))
    if not files:
        raise InputError(metadata_dir, "no ROMI metadata (NNNNN_rgb.json) in the folder")
    cameras, images = [], []
    for k, path in enumerate(files, 1):
        try:
            calibrated = read_json(path)["colmap_camera"]
            model = calibrated["camera_model"]
            rotation = np.asarray(calibrated["rotmat"], np.float64).reshape(3, 3)
            translation = np.asarray(calibrated["tvec"], np.float64).reshape(3)
            camera = (model["model"], int(model["width"]), int(model["height"]),
                      tuple(float(v) for v in model["params"]))
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(path, f'"colmap_camera" needs camera_model, rotmat and tvec '
                             f"({err})") from None
        if camera not in cameras:
            cameras.append(camera)
        quaternion = " ".join(repr(float(v)) for v in matrix_to_quaternion(rotation))
        t = " ".join(repr(float(v)) for v in translation)
        images.append(f"{k} {quaternion} {t} "
                      f"{cameras.index(camera) + 1} {path.stem}.jpg\n\n")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text(out_dir / "cameras.txt", "".join(
        f"{k} {m} {w} {h} {' '.join(map(repr, params))}\n"
        for k, (m, w, h, params) in enumerate(cameras, 1)))
    write_text(out_dir / "images.txt", "".join(images))
    write_text(out_dir / "points3D.txt", "")
    return out_dir


def romi_rough_poses(metadata_dir: Path, out_csv: Path) -> Path:
    """The ROMI scanner's own log of a scan (metadata/NNNNN_rgb.json: "approximate_pose"
    x, y, z in millimetres, pan and tilt in degrees) as a rough-poses CSV for
    `flowerpose frames --images ... --poses CSV --pose-units mm`. Only the logged pose is
    used, not the calibration the files also hold."""
    from flowerpose.atomic import write_text
    from flowerpose.jsonio import read_json

    rows = ["file,x,y,z,pan,tilt"]
    files = sorted(Path(metadata_dir).glob("*.json"))
    if not files:
        raise InputError(metadata_dir, "no ROMI metadata (NNNNN_rgb.json) in the folder")
    for path in files:
        pose = read_json(path).get("approximate_pose")
        if not isinstance(pose, list) or len(pose) != 5:
            raise InputError(path, '"approximate_pose" needs x, y, z, pan, tilt')
        x, y, z, pan, tilt = (float(v) for v in pose)
        heading = (pan + ROMI_PAN_TO_HEADING_DEG) % 360
        rows.append(f"{path.stem}.jpg,{x!r},{y!r},{z!r},{heading!r},{tilt!r}")
    return write_text(out_csv, "\n".join(rows) + "\n")
