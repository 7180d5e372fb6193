"""`flowerpose label DIR`: label a real plant's flowers in a local web page.

The page (`assets/label/page.html`, with plotly's JavaScript from the installed package:
nothing is loaded from the internet) shows the folder's cloud in 3D, decimated for display
(`MAX_SHOWN_POINTS`; labels always refer to the full cloud), pre-filled with the folder's
labels.json (any format a real plant folder takes) or, where there is none, a
flowers.json's detections (the folder's, or `--detections`) as proposals. The server binds
127.0.0.1 on a free port and answers:

    GET  /               the page
    GET  /state          the cloud shown (positions in the cloud's unit, colours), the
                         flowers to start from, the folder, the unit, the labeller
    POST /fit            {"center": [x, y, z], "towards": [nx, ny, nz] or null}: the plane
                         through the full cloud's points within a corolla's radius of the
                         centre (`fit.fit_plane`, robust), its normal turned towards
                         `towards`; {"normal": null} where too few points are there
    POST /save           {"flowers": [...], "session": {...}}: labels.json written
                         (`labels.write_labels`: atomic, the earlier file kept as a backup)

Every coordinate the page and the files see is the cloud's own (its unit, its frame);
`truth_scale` 1.

The server answers its own page only. Any web page the labeller has open can send a
request to 127.0.0.1, and a name that resolves to it (DNS rebinding) can read the answer,
so every request must name the server itself as its `Host` (127.0.0.1 or localhost, with
its port) and, where a browser says where it comes from, its `Origin` too; every POST must
be JSON (`Content-Type: application/json`, which a page of another origin cannot send
without asking first) and carry the session's token (`X-Flowerpose-Token`), a random
string written into the page this server gave out and nowhere else. Anything else is
refused with 403 and changes nothing.
"""

from __future__ import annotations

import json
import secrets
import threading
from dataclasses import dataclass
from datetime import UTC, datetime
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.cloudio import Cloud, Units, read_cloud_and_unit
from flowerpose.errors import InputError
from flowerpose.eval.labelling.agreement import read_labelling
from flowerpose.eval.scoring.labels import STATES, Label, LabelFile, read_labels, write_labels
from flowerpose.eval.scoring.real_source import folder_clouds, source_truth_scale
from flowerpose.log import LOG

#: Most cloud points the page draws (a seeded subsample above it): plotly stays responsive.
MAX_SHOWN_POINTS = 150_000
#: Radius round a flower's centre whose points a snap fits, metres (a strawberry corolla's,
#: 10-15 mm, with a margin).
FIT_RADIUS_M = 0.015
#: Fewest points a snap fits a plane to.
MIN_FIT_POINTS = 12


@dataclass
class LabelSession:
    """A folder being labelled: its full cloud (its own unit) and where labelling starts."""

    folder: Path
    cloud: Cloud
    """The folder's points in the cloud's own unit and frame."""
    metres_per_unit: float
    start: list[dict[str, Any]]
    """The flowers to start from: {"id", "center", "normal", "state"} ("proposed" for a
    detection nobody has judged yet)."""
    started_from: str
    labeller: str

    def __post_init__(self) -> None:
        self.tree = cKDTree(self.cloud.points)
        self.lock = threading.Lock()


def _read_folder_cloud(folder: Path, units: Units) -> tuple[Cloud, float]:
    """The folder's points in their own unit (cloud.ply, or its candidates or crops
    together) and the metres one unit is."""
    _, paths = folder_clouds(folder)
    clouds, scales = [], []
    for path in paths:
        cloud, scale = read_cloud_and_unit(path, units)
        clouds.append(Cloud(cloud.points / scale, cloud.colors))
        scales.append(scale)
    if len(set(scales)) > 1:
        raise InputError(folder, "its cloud files are in different units; give --units")
    return (Cloud(np.concatenate([c.points for c in clouds]),
                  np.concatenate([c.colors for c in clouds])), scales[0])


def _starting_flowers(folder: Path, metres_per_unit: float, detections: Path
                      ) -> tuple[list[dict], str]:
    """labels.json's flowers (in the cloud's unit), else the detections' (a flowers.json)
    as proposals, else none; and which it was."""
    labels = folder / "labels.json"
    if labels.is_file():
        labelling = read_labelling(labels, source_truth_scale(folder), folder=True)
        states = {}
        if labelling.format == "flowerpose":
            states = {f.id: f.state for f in read_labels(labels).flowers}
        return [{"id": str(i), "center": [float(v) for v in c],
                 "normal": None if n is None else [float(v) for v in n],
                 "state": states.get(i, "labelled" if n is not None else "unlabelled")}
                for i, c, n in zip(labelling.ids, labelling.centers, labelling.normals,
                                   strict=True)], f"{labels.name} ({labelling.format})"
    if detections.is_file():
        from flowerpose.pipeline.flowers import read_flowers

        proposals = []
        for k, flower in enumerate(read_flowers(detections)):
            normal = flower["normals"].get("plane")
            proposals.append({"id": f"d{flower.get('id', k)}",
                              "center": [float(v) / metres_per_unit for v in flower["center"]],
                              "normal": None if normal is None else [float(v) for v in normal],
                              "state": "proposed"})
        return proposals, f"{detections} (detections)"
    return [], f"nothing (no labels.json, no {detections})"


def open_session(folder: str | Path, labeller: str, units: Units = "auto",
                 detections: str | Path | None = None) -> LabelSession:
    """A folder to label: its cloud read and where labelling starts (its labels.json, else
    `detections`, default folder/flowers.json); InputError naming the folder or file for a
    folder without points, an unreadable labels.json, or detections given and not there."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "no such folder (a plant folder with cloud.ply, candidates/ "
                         "or crops/)")
    if detections is not None and not Path(detections).is_file():
        raise InputError(detections, "file not found (a flowers.json from flowerpose detect)")
    cloud, scale = _read_folder_cloud(folder, units)
    start, started_from = _starting_flowers(
        folder, scale, Path(detections) if detections is not None else folder / "flowers.json")
    return LabelSession(folder, cloud, scale, start, started_from, labeller)


def shown_points(session: LabelSession) -> np.ndarray:
    """Indices of the points the page draws: all, or a seeded subsample of
    MAX_SHOWN_POINTS."""
    count = len(session.cloud)
    if count <= MAX_SHOWN_POINTS:
        return np.arange(count)
    return np.sort(np.random.default_rng(0).choice(count, MAX_SHOWN_POINTS, replace=False))


def fit_normal(session: LabelSession, center: np.ndarray, towards: np.ndarray | None
               ) -> tuple[np.ndarray | None, int]:
    """The normal of the plane through the points within FIT_RADIUS_M of `center` (the
    cloud's unit), turned towards `towards`, and how many points it used."""
    from flowerpose.pipeline.fit import fit_plane

    radius = FIT_RADIUS_M / session.metres_per_unit
    near = session.tree.query_ball_point(center, r=radius)
    if len(near) < MIN_FIT_POINTS:
        return None, len(near)
    normal = fit_plane(session.cloud.points[near], robust_iterations=5)
    if normal is None:
        return None, len(near)
    if towards is not None and float(normal @ towards) < 0:
        normal = -normal
    return normal, len(near)


def save_labels(session: LabelSession, body: dict[str, Any]) -> dict[str, Any]:
    """Write labels.json from the page's flowers (those decided: labelled, unlabelled or
    rejected; proposals nobody judged are left out) and its session; returns what was
    written."""
    flowers = body.get("flowers")
    if not isinstance(flowers, list):
        raise InputError("save", 'expected {"flowers": [...], "session": {...}}')
    now = datetime.now(UTC).isoformat(timespec="seconds")
    labels, undecided = [], 0
    for k, flower in enumerate(flowers):
        state = flower.get("state")
        if state == "proposed":
            undecided += 1
            continue
        if state not in STATES:
            raise InputError("save", f"flower {k}: unknown state {state!r}")
        normal = flower.get("normal")
        name = str(flower.get("id", k))
        if state == "labelled" and normal is not None:
            normal = np.asarray(normal, float)
            if normal.shape != (3,) or not np.isfinite(normal).all() \
                    or np.linalg.norm(normal) < 1e-9:
                raise InputError("save", f"flower {name}: its normal {normal.tolist()} is no "
                                 "direction (three finite numbers, not all 0)")
            normal = normal / np.linalg.norm(normal)
        labels.append(Label(
            id=name, center=np.asarray(flower["center"], float),
            normal=None if state != "labelled" or normal is None else normal,
            state=state, labeller=str(flower.get("labeller") or session.labeller),
            time=str(flower.get("time") or now)))
    missing = [f.id for f in labels if f.state == "labelled" and f.normal is None]
    if missing:
        raise InputError("save", f"flower {missing[0]} is labelled without a normal")
    path = session.folder / "labels.json"
    sessions = []
    if path.is_file() and read_labelling(path).format == "flowerpose":
        sessions = read_labels(path).sessions
    record = {"labeller": session.labeller, "saved": now, **(body.get("session") or {})}
    with session.lock:
        backup = write_labels(path, LabelFile(labels, 1.0, [*sessions, record]))
    counts = {state: sum(f.state == state for f in labels) for state in STATES}
    return {"file": str(path), "backup": None if backup is None else str(backup),
            "counts": counts, "undecided": undecided, "session": record}


#: The header every POST carries the session's token in.
TOKEN_HEADER = "X-Flowerpose-Token"
#: The names the server answers to (with its port).
LOCAL_NAMES = ("127.0.0.1", "localhost")


def _page(token: str) -> bytes:
    from plotly.offline import get_plotlyjs

    template = (files("flowerpose.assets") / "label" / "page.html").read_text(encoding="utf-8")
    return (template.replace("/*PLOTLY*/", get_plotlyjs())
            .replace("/*TOKEN*/", json.dumps(token)).encode("utf-8"))


def refusal(headers: Any, port: int, method: str, token: str) -> str | None:
    """Why a request may not be answered (module docstring), None where it may: a `Host`
    other than this server, an `Origin` other than its page's, a POST that is not JSON or
    lacks the session's token."""
    allowed = {f"{name}:{port}" for name in LOCAL_NAMES}
    if headers.get("Host") not in allowed:
        return f"Host {headers.get('Host')!r} is not this server"
    origin = headers.get("Origin")
    if origin is not None and origin not in {f"http://{name}" for name in allowed}:
        return f"Origin {origin!r} is not this server's page"
    if method == "POST":
        kind = (headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if kind != "application/json":
            return "a POST must be JSON (Content-Type: application/json)"
        if not secrets.compare_digest(headers.get(TOKEN_HEADER) or "", token):
            return f"a POST must carry this session's token ({TOKEN_HEADER})"
    return None


def _state(session: LabelSession) -> dict[str, Any]:
    shown = shown_points(session)
    points = session.cloud.points[shown]
    return {"folder": str(session.folder), "labeller": session.labeller,
            "metres_per_unit": session.metres_per_unit, "points": len(session.cloud),
            "shown": len(shown), "started_from": session.started_from,
            "x": points[:, 0].round(6).tolist(), "y": points[:, 1].round(6).tolist(),
            "z": points[:, 2].round(6).tolist(),
            "rgb": [f"rgb({r},{g},{b})" for r, g, b in session.cloud.colors[shown]],
            "flowers": session.start, "fit_radius": FIT_RADIUS_M / session.metres_per_unit}


def make_server(session: LabelSession, port: int = 0, token: str | None = None
                ) -> ThreadingHTTPServer:
    """The page's server on 127.0.0.1 (`port` 0: a free one); not yet serving. `token`: the
    session's (default: a fresh random one, in the page it serves)."""
    token = token or secrets.token_urlsafe(32)
    page = _page(token)

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
            LOG.debug("label: " + format % args)

        def _send(self, status: int, body: bytes, kind: str = "application/json") -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, status: int, data: Any) -> None:
            self._send(status, json.dumps(data).encode("utf-8"))

        def _refused(self, method: str) -> bool:
            why = refusal(self.headers, self.server.server_address[1], method, token)
            if why is not None:
                LOG.warning(f"label: refused {method} {self.path}: {why}")
                self._json(HTTPStatus.FORBIDDEN, {"error": why})
            return why is not None

        def do_GET(self) -> None:  # noqa: N802
            if self._refused("GET"):
                return
            if self.path == "/":
                self._send(HTTPStatus.OK, page, "text/html; charset=utf-8")
            elif self.path == "/state":
                self._json(HTTPStatus.OK, _state(session))
            else:
                self._json(HTTPStatus.NOT_FOUND, {"error": f"no {self.path}"})

        def do_POST(self) -> None:  # noqa: N802
            if self._refused("POST"):
                return
            try:
                length = int(self.headers.get("Content-Length", 0))
                body = json.loads(self.rfile.read(length) or b"{}")
                if not isinstance(body, dict):
                    raise ValueError("the body must be a JSON object")
                if self.path == "/fit":
                    towards = body.get("towards")
                    normal, used = fit_normal(session, np.asarray(body["center"], float),
                                              None if towards is None
                                              else np.asarray(towards, float))
                    self._json(HTTPStatus.OK, {"normal": None if normal is None
                                               else normal.tolist(), "points": used})
                elif self.path == "/save":
                    self._json(HTTPStatus.OK, save_labels(session, body))
                else:
                    self._json(HTTPStatus.NOT_FOUND, {"error": f"no {self.path}"})
            except (InputError, OSError, KeyError, TypeError, ValueError) as error:
                self._json(HTTPStatus.BAD_REQUEST, {"error": str(error)})

    server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    server.token = token
    return server
