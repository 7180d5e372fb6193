"""Point-cloud files: read with validation, write binary PLY. Shared by every package."""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from flowerpose.atomic import write_file, write_text
from flowerpose.errors import InputError
from flowerpose.log import LOG, library_output, open3d

#: Largest extent (metres) a single-plant scan in metres can plausibly have.
MAX_METRIC_EXTENT_M = 5.0
#: Extents (file units) that identify a scan written in millimetres.
MM_EXTENT_RANGE = (50.0, 10_000.0)

#: A cloud's unit: "m", "mm", "auto" (decided from its extent), or a number, the metres one
#: unit of the cloud is (a photogrammetry cloud's arbitrary unit, measured once by hand).
Units = Literal["auto", "m", "mm"] | float


@dataclass(frozen=True)
class Cloud:
    """A coloured point cloud.

    points: (N, 3) float64, metres, bed frame (x along the bed, y across, z up, z = 0 on soil).
    colors: (N, 3) uint8 RGB.
    """

    points: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, index: np.ndarray) -> Cloud:
        return Cloud(self.points[index], self.colors[index])

    def first_copies(self) -> np.ndarray:
        """Sorted indices of the first copy of every distinct point (a point that several
        views' files hold is there once)."""
        return np.sort(np.unique(self.points, axis=0, return_index=True)[1])


def read_cloud(path: str | Path, units: Units = "auto", allow_empty: bool = False) -> Cloud:
    """Read a coloured cloud (.ply or .pcd) and check it is usable.

    Refuses missing or unreadable files, clouds without colours, NaN or infinite
    coordinates and empty clouds, with an InputError naming the file. With units="auto"
    a cloud whose extent says millimetres is converted to metres and a note is printed
    on stderr; an extent that fits neither unit is refused.
    """
    return read_cloud_and_unit(path, units, allow_empty)[0]


def read_cloud_and_unit(path: str | Path, units: Units = "auto", allow_empty: bool = False
                        ) -> tuple[Cloud, float]:
    """`read_cloud`, and the metres one of the file's units is (what `units` decided)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a file")
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise InputError(path, "expected a .ply or .pcd point cloud")
    try:
        with open(path, "rb") as handle:
            head = handle.read(4)
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})") from None
    header = None
    if path.suffix.lower() == ".ply":
        if head[:3] != b"ply":
            raise InputError(path, "not a PLY file (no 'ply' header)")
        header = ply_header(path)
    if header is not None and header.vertices and header.colour_prefix:
        cloud = _read_renamed_colours(path, header)
    else:
        if header is None and _pcd_coordinate_bytes(path) == 8:
            # Open3D reads a PCD's 64-bit coordinates as zeros, without a word.
            raise InputError(path, "its coordinates are 64-bit, which the PCD reader "
                             "(Open3D) reads as zeros; save the cloud as PLY (doubles keep "
                             "their precision there) or with 32-bit coordinates near the origin")
        cloud = None if header is not None and header.vertices == 0 else _read_o3d(path)
    if header is not None and header.ascii_rows is not None:
        held, declared = header.ascii_rows
        if held != declared:
            raise InputError(path, f"the header declares {declared} rows ({header.vertices} "
                             f"points), the file holds {held}: its header and body disagree")
    points = np.zeros((0, 3)) if cloud is None else np.asarray(cloud.points, dtype=np.float64)
    if cloud is None or len(points) == 0:
        if allow_empty:
            return Cloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8)), 1.0
        raise InputError(path, "the cloud has no points (empty or unreadable file)")
    if not cloud.has_colors():
        raise InputError(path, "the cloud has no colours; the pipeline needs RGB per point")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} of {len(points)} points have NaN or infinite "
                         "coordinates; clean the cloud first")
    colors = np.asarray(cloud.colors) * 255.0
    if header is not None and header.float_colours and colors.max(initial=0.0) <= 1.0 + 1e-6:
        # Open3D divides every colour by 255; colours stored as floats in 0-1 were not bytes.
        colors = colors * 255.0
    elif header is not None and header.wide_colours:
        colors = colors / 257.0  # 16-bit to 8-bit: 65535 is 255
    colors = np.clip(colors + 0.5, 0, 255).astype(np.uint8)
    scale = metres_per_unit(points, units, path)
    single = (header.coordinate_type in ("float", "float32") if header is not None
              else _pcd_coordinate_bytes(path) == 4)
    if single:
        _check_precision(points, scale, path)
    return Cloud(points * scale if scale != 1.0 else points, colors), scale


def _read_o3d(path: Path):
    """Open3D's point cloud of a file. Open3D reads what it can of a damaged file and says
    so only in its log, in its words: that is one error line here, naming the file."""
    o3d = open3d()
    with library_output(r"^(RPly: |\[Open3D )") as said, o3d.utility.VerbosityContextManager(
            o3d.utility.VerbosityLevel.Warning):
        cloud = o3d.io.read_point_cloud(str(path))
    problem = _read_problem(said)
    if problem is not None:
        raise InputError(path, f"cannot be read: {problem}")
    return cloud


def _read_problem(said: list[str]) -> str | None:
    """Why a read failed, from what Open3D and RPly (its PLY parser) said meanwhile:
    RPly's reason where it gave one ("error reading 'z' of 'vertex' number 1"), else
    Open3D's ("unable to parse header"); None when the read did not fail."""
    failed = [line for line in said if re.search(r"Read P[A-Z]+ failed", line)]
    for line in said:
        if line.startswith("RPly: "):
            reason = line.removeprefix("RPly: ").strip().rstrip(".")
            return reason[:1].lower() + reason[1:]
    if failed:
        return failed[0].split("failed:", 1)[-1].split(":")[0].strip().rstrip(".") or \
            "unreadable"
    return None


def to_metres(points: np.ndarray, units: Units, source: str | Path) -> np.ndarray:
    """Points in metres, deciding the file's unit from its extent when units="auto", or
    multiplied by `units` where it is a number (metres a unit); a unit the extent
    contradicts (a metre cloud said to be in millimetres) is refused."""
    scale = metres_per_unit(points, units, source)
    return points * scale if scale != 1.0 else points


#: Coarsest step 32-bit coordinates may come in where the cloud reaches, metres: a flower's
#: corolla is 20-30 mm across, and the detect stage's grid pixel is 1 mm.
FLOAT32_STEP_LIMIT_M = 0.001


def _pcd_coordinate_bytes(path: Path) -> int | None:
    """Bytes of a PCD file's x coordinate (its header's SIZE for FIELDS x: 4 for float32,
    8 for doubles); None where the header does not say."""
    fields: list[str] = []
    sizes: list[str] = []
    try:
        with open(path, "rb") as handle:
            for _ in range(64):  # the header: a few lines, up to DATA
                words = handle.readline().decode("ascii", "replace").split()
                if not words or words[0] == "DATA":
                    break
                if words[0] == "FIELDS":
                    fields = words[1:]
                elif words[0] == "SIZE":
                    sizes = words[1:]
    except OSError:
        return None
    if "x" not in fields or len(sizes) != len(fields):
        return None
    size = sizes[fields.index("x")]
    return int(size) if size.isdigit() else None


def _check_precision(points: np.ndarray, metres_per_unit: float, path: Path) -> None:
    """Refuse 32-bit coordinates so far from the origin that their steps blur flowers (a
    cloud at map coordinates: 500,000 m east, 4,000,000 m north, in steps of 0.25-0.5 m)."""
    reach = float(np.abs(points).max()) if len(points) else 0.0
    step = float(np.spacing(np.float32(reach))) * metres_per_unit
    if step > FLOAT32_STEP_LIMIT_M:
        raise InputError(path, f"its coordinates are 32-bit floats reaching {reach:.6g}, where "
                         f"they come in steps of {step * 1000:.3g} mm: too coarse for flowers; "
                         "save the cloud with doubles, or moved near the origin (its centre "
                         "subtracted)")


def _read_renamed_colours(path: Path, header: PlyHeader):
    """Open3D's cloud of a PLY whose colours are named diffuse_red, ...: read through a copy
    whose header calls them red, green, blue (the data is the same bytes), in the system's
    temporary folder."""
    import tempfile

    with open(path, "rb") as handle:
        head = re.sub(rf"\b{header.colour_prefix}(red|green|blue)\b", r"\1",
                      handle.read(header.header_bytes).decode("ascii", "replace"))
        with tempfile.NamedTemporaryFile(suffix=".ply") as copy:
            copy.write(head.encode("ascii"))
            shutil.copyfileobj(handle, copy)
            copy.flush()
            return _read_o3d(Path(copy.name))


def require_hue(cloud: Cloud, source: str | Path) -> None:
    """Refuse a cloud whose every point is grey (its red, green and blue within
    GREY_TOLERANCE): the pipeline tells flowers from leaves by colour, so it would find
    nothing and say nothing."""
    if len(cloud) == 0:
        return
    colours = cloud.colors.astype(np.int16)
    if int((colours.max(axis=1) - colours.min(axis=1)).max()) <= GREY_TOLERANCE:
        raise InputError(source, "every point is grey (red, green and blue equal): flowers "
                         "are told from leaves by colour; export the cloud with its colours")


#: Channels (0-255) within this of each other count as grey.
GREY_TOLERANCE = 3


def metres_per_unit(points: np.ndarray, units: Units, source: str | Path) -> float:
    """The metres one unit of `points` is (`to_metres`)."""
    extent = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    if isinstance(units, int | float) and not isinstance(units, bool):
        if not (units > 0 and np.isfinite(units)):
            raise InputError(source, f"units {units!r}: metres a unit must be a positive number")
        if extent * units > MAX_METRIC_EXTENT_M:
            raise InputError(source, f"extent {extent:.3g} units is {extent * units:.3g} m at "
                             f"{units:g} m a unit: not a plant; is the unit right?")
        return float(units)
    if units == "m":
        if extent > MM_EXTENT_RANGE[0]:
            raise InputError(source, f"extent {extent:.3g} units is {extent:.3g} m in metres: "
                             "not a plant; is it in millimetres (--units mm or auto)?")
        return 1.0
    if units == "mm":
        if len(points) > 1 and extent < MAX_METRIC_EXTENT_M:
            raise InputError(source, f"extent {extent:.3g} units is {extent:.3g} mm in "
                             "millimetres: not a plant; is it in metres (--units m or auto)?")
        return 1e-3
    if extent <= MAX_METRIC_EXTENT_M:
        return 1.0
    if MM_EXTENT_RANGE[0] <= extent <= MM_EXTENT_RANGE[1]:
        LOG.warning(f"note: {source}: extent {extent:.0f} units looks like millimetres; "
                    "converted to metres")
        return 1e-3
    raise InputError(source, f"extent {extent:.3g} units fits neither metres (<= "
                     f"{MAX_METRIC_EXTENT_M:g}) nor millimetres ({MM_EXTENT_RANGE[0]:g}-"
                     f"{MM_EXTENT_RANGE[1]:g}); rescale the cloud to metres")


#: Bytes of each PLY scalar type.
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
              "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
              "float": 4, "float32": 4, "double": 8, "float64": 8}


@dataclass(frozen=True)
class PlyHeader:
    """What a PLY file's header promises."""

    format: str
    vertices: int
    float_colours: bool
    """The vertex colours are stored as floats (0-1), not bytes."""
    expected_bytes: int | None
    """The file's size if every element is there (binary files of fixed-size rows)."""
    wide_colours: bool = False
    """The vertex colours are 16-bit (ushort, 0-65535)."""
    ascii_rows: tuple[int, int] | None = None
    """An ASCII file's rows: (held by its body, declared by its header)."""
    coordinate_type: str | None = None
    """The type the x coordinate is stored as ("float", "double", ...)."""
    colour_prefix: str = ""
    """What the colour properties' names start with where they are not red, green, blue
    ("diffuse_": diffuse_red, diffuse_green, diffuse_blue, as some tools write them)."""
    header_bytes: int = 0
    """The header's length, bytes."""


def ply_header(path: Path) -> PlyHeader:
    """The header of a PLY file, and the size its data must have; a binary file shorter
    than that is truncated (Open3D reads the missing points as zeros without a word)."""
    try:
        with open(path, "rb") as handle:
            lines = []
            while (line := handle.readline()) and len(lines) < 10_000:
                lines.append(line.decode("ascii", "replace").strip())
                if lines[-1] == "end_header":
                    break
            header_bytes = handle.tell()
        size = path.stat().st_size
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})") from None
    if not lines or lines[-1] != "end_header":
        raise InputError(path, "not a PLY file (its header never ends)")
    fmt, vertices, row_bytes, fixed, element = "ascii", 0, {}, True, None
    colour_types, coordinate_type, names = {}, None, set()
    for words in (line.split() for line in lines):
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            element = words[1]
            try:
                row_bytes[element] = [int(words[2]), 0]
            except ValueError:
                raise InputError(path, f"bad PLY header line {' '.join(words)!r}") from None
            if element == "vertex":
                vertices = int(words[2])
        elif words[:1] == ["property"] and element is not None:
            if words[1] == "list" or words[1] not in _PLY_SIZES:
                fixed = False
                continue
            row_bytes[element][1] += _PLY_SIZES[words[1]]
            if element == "vertex":
                names.add(words[-1])
                coordinate_type = words[1] if words[-1] == "x" else coordinate_type
            colour = words[-1].removeprefix(COLOUR_ALIAS)
            if element == "vertex" and colour in ("red", "green", "blue"):
                colour_types[colour] = words[1]
    expected = None
    width = row_bytes.get("vertex", [0, 1])[1] or 1
    if fmt.startswith("binary") and fixed:
        expected = header_bytes + sum(count * width for count, width in row_bytes.values())
        if size < expected:
            held = max(0, (size - header_bytes) // width)
            raise InputError(path, f"truncated: the header declares {vertices} points, the "
                             f"file holds {min(held, vertices)}")
        if size - expected >= width and len(row_bytes) == 1:
            raise InputError(path, f"the header declares {vertices} points, the file holds "
                             f"{vertices + (size - expected) // width}: its header and body "
                             "disagree")
    rows = None
    if fmt == "ascii" and any(line.startswith("format ") for line in lines):
        rows = (_ascii_rows(path, header_bytes), sum(count for count, _ in row_bytes.values()))
    kinds = set(colour_types.values())
    if kinds - _COLOUR_TYPES:
        raise InputError(path, f"colours of type {sorted(kinds - _COLOUR_TYPES)[0]}: expected "
                         "8-bit (uchar), 16-bit (ushort) or float colours")
    if len(kinds) > 1:
        raise InputError(path, f"colour channels of different types ({', '.join(sorted(kinds))})")
    float_colours = any(t.startswith(("float", "double")) for t in colour_types.values())
    wide = any(t in ("ushort", "uint16") for t in colour_types.values())
    prefix = COLOUR_ALIAS if not names & {"red", "green", "blue"} and {
        COLOUR_ALIAS + c for c in ("red", "green", "blue")} <= names else ""
    return PlyHeader(fmt, vertices, float_colours, expected, wide, rows, coordinate_type,
                     prefix, header_bytes)


#: Another name some tools (MeshLab, Blender) give the colour properties: diffuse_red, ...
COLOUR_ALIAS = "diffuse_"


#: Colour property types a cloud may have: 8-bit, 16-bit and float (0-1).
_COLOUR_TYPES = {"uchar", "uint8", "ushort", "uint16", "float", "float32", "double", "float64"}


def _ascii_rows(path: Path, header_bytes: int) -> int:
    """The non-empty lines after an ASCII PLY's header: its rows."""
    with open(path, "rb") as handle:
        handle.seek(header_bytes)
        return sum(1 for line in handle if line.strip())


def write_cloud(path: str | Path, cloud: Cloud) -> Path:
    """Write a binary PLY (float64 xyz, uint8 rgb as Open3D stores it), whole; an empty
    cloud as a PLY of no points (Open3D writes no empty geometry)."""
    if len(cloud) == 0:
        return write_text(path, empty_ply(colours=True))
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(cloud.points, np.float64)))
    pcd.colors = o3d.utility.Vector3dVector(np.asarray(cloud.colors, np.float64) / 255.0)
    return write_file(path, lambda tmp: o3d.io.write_point_cloud(str(tmp), pcd,
                                                                 write_ascii=False))


def empty_ply(colours: bool = False, faces: bool = False) -> str:
    """A PLY file of no points (and no faces), which every reader opens as empty."""
    rgb = "property uchar red\nproperty uchar green\nproperty uchar blue\n" if colours else ""
    face = "element face 0\nproperty list uchar int vertex_indices\n" if faces else ""
    return ("ply\nformat ascii 1.0\nelement vertex 0\nproperty double x\nproperty double y\n"
            f"property double z\n{rgb}{face}end_header\n")
