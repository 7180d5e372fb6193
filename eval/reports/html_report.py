"""report.html: one self-contained page to look at a run (an eval, or a detection).

Table I, the errors with their intervals, the comparisons, the accuracy curves, the
per-flower table, the error histograms and, per plant, an interactive 3D view of the cloud
(subsampled) with each flower's estimated normal (red) and true normal (green) drawn from
its centre and its id beside it, the detections that are false positives (orange) or
extra (purple) circled, labelled flowers that are not scored (grey), the camera path of a
scanned plant (blue: the frames its cloud was made from), and the grid views with their
numbered detections. The figures are plotly's (the standard for interactive figures from Python);
its JavaScript is embedded once in the page, so it opens from disk with no server and no
network.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.atomic import write_text
from flowerpose.cloudio import Cloud
from flowerpose.eval.reports.report import (
    COMPARISON_LEGEND,
    INTERVAL_LEGEND,
    METHODS,
    TABLE_LEGEND,
    comparison_rows,
    interval_rows,
    note_lines,
    pollination_lines,
    summary_lines,
    table_rows,
)
from flowerpose.eval.scoring.truth import TruthFlower

#: Most cloud points a plant's 3D view draws (a seeded subsample above it).
MAX_VIEW_POINTS = 12000
ESTIMATE_COLOUR, TRUTH_COLOUR = "rgb(220,30,30)", "rgb(20,160,60)"
FALSE_POSITIVE_COLOUR, EXTRA_COLOUR, LOST_COLOUR = "rgb(255,140,0)", "rgb(150,60,200)", "gray"
CAMERA_COLOUR = "rgb(40,90,210)"


@dataclass
class PlantView:
    """What a plant's section shows: its cloud, the flowers found (flowers.json entries, as
    `read_flowers` gives them) and, for a scored run, the truth."""

    name: str
    cloud: Cloud
    flowers: list[dict]
    truth: list[TruthFlower] | None = None
    views_png: Path | None = None
    """The grid views with their detections (`views/views.png`), when the run made them."""
    cameras: np.ndarray | None = None
    """(K, 4, 4) camera-to-cloud poses (metres; OpenCV axes: z the viewing direction) of the
    frames the cloud was made from, in the order they were taken; None for a cloud made
    without a camera (oracle, real)."""


@dataclass
class BedSpot:
    """A plant's place in the bed: its name, centre (x, y) and radius, metres, bed frame."""

    name: str
    x: float
    y: float
    radius: float


@dataclass
class BedSection:
    """The bed's part of a field run's page: a top-down map and a row a plant."""

    spots: list[BedSpot]
    header: list[str]
    rows: list[list[str]]
    """A row a plant, its first cell the plant's name (linked to the plant's section)."""
    notes: list[str]
    """Sentences under the table (the bed's times)."""


def write_html_report(path: Path, title: str, report: dict | None,
                      plants: list[PlantView], bed: BedSection | None = None) -> Path:
    """Write report.html: `report` is report.json's content (None for a detection, which
    has no scores); `bed`: a field run's bed, shown first."""
    parts = [f"<h1>{_e(title)}</h1>"]
    if bed is not None:
        parts += _bed(bed, plants)
    if report is not None:
        parts += _scores(report)
        parts += _pollination(report, Path(path).parent / "pollination.png")
    for plant in plants:
        entry = _entry(report, plant.name)
        parts.append(f'<h2 id="{_e(_anchor(plant.name))}">{_e(plant.name)}</h2>')
        parts.append(_flower_table(plant, report, entry))
        parts.append(_figure_html(_view_3d(plant, entry), f"view-{plant.name}"))
        if plant.views_png is not None and plant.views_png.is_file():
            encoded = base64.b64encode(plant.views_png.read_bytes()).decode("ascii")
            parts.append(f'<p>Grid views with the numbered detections</p><img class="views" '
                         f'src="data:image/png;base64,{encoded}" alt="grid views">')
    if report is not None:
        parts.append("<h2>Configuration</h2><details><summary>settings of this run</summary>"
                     f"<pre>{_e(json.dumps(report.get('config', {}), indent=1))}</pre>"
                     "</details>")
    from plotly.offline import get_plotlyjs

    return write_text(path, _PAGE.format(title=_e(title), plotly=get_plotlyjs(),
                                         body="\n".join(parts)))


def _anchor(name: str) -> str:
    return f"plant-{name}"


def _bed(bed: BedSection, plants: list[PlantView]) -> list[str]:
    """The bed's map, its table (each plant linked to its section) and its notes."""
    shown = {p.name for p in plants}
    head = "".join(f"<th>{_e(h)}</th>" for h in bed.header)
    body = "".join(
        "<tr>" + "".join(
            (f'<td><a href="#{_e(_anchor(c))}">{_e(c)}</a></td>' if k == 0 and c in shown
             else f"<td>{_e(c)}</td>") for k, c in enumerate(row)) + "</tr>"
        for row in bed.rows)
    return ["<h2>The bed</h2>", _figure_html(bed_map(bed.spots, plants), "bed-map"),
            f'<table id="bed"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>',
            "<ul>" + "".join(f"<li>{_e(n)}</li>" for n in bed.notes) + "</ul>"]


#: How long a horizontal normal is drawn on the bed map, metres; a normal's top-down
#: projection is drawn at this times its horizontal part, so an upward flower is a dot.
MAP_NORMAL_M = 0.08


def bed_map(spots: list[BedSpot], plants: list[PlantView]):
    """Top-down map of the bed (x along it, y across, metres): each plant's circle and name,
    its flowers' centres and the top-down projection of their estimated normals (red) and,
    where scored, of the true ones (green)."""
    import plotly.graph_objects as go

    figure = go.Figure()
    for spot in spots:
        figure.add_shape(type="circle", x0=spot.x - spot.radius, x1=spot.x + spot.radius,
                         y0=spot.y - spot.radius, y1=spot.y + spot.radius,
                         line={"color": "rgb(90,140,60)"}, fillcolor="rgba(90,140,60,0.12)")
    figure.add_trace(go.Scatter(x=[s.x for s in spots], y=[s.y + s.radius for s in spots],
                                mode="text", text=[s.name for s in spots],
                                textposition="top center", showlegend=False,
                                hoverinfo="skip"))
    estimated = [(f"{p.name}: {f.get('id', k)}", np.asarray(f["center"], float),
                  np.asarray(f["normals"]["plane"], float))
                 for p in plants for k, f in enumerate(p.flowers)
                 if f["normals"].get("plane") is not None]
    truth = [(f"{p.name}: {t.id}", np.asarray(t.center, float), np.asarray(t.normal, float))
             for p in plants for t in (p.truth or []) if t.visible]
    for flowers, colour, name in ((estimated, ESTIMATE_COLOUR, "estimated normal (plane)"),
                                  (truth, TRUTH_COLOUR, "true normal")):
        if not flowers:
            continue
        x: list[float | None] = []
        y: list[float | None] = []
        for _, centre, normal in flowers:
            x += [centre[0], centre[0] + MAP_NORMAL_M * normal[0], None]
            y += [centre[1], centre[1] + MAP_NORMAL_M * normal[1], None]
        figure.add_trace(go.Scatter(x=x, y=y, mode="lines", name=name,
                                    line={"color": colour, "width": 2}, hoverinfo="skip"))
        figure.add_trace(go.Scatter(x=[c[0] for _, c, _ in flowers],
                                    y=[c[1] for _, c, _ in flowers], mode="markers",
                                    text=[label for label, _, _ in flowers], hoverinfo="text",
                                    marker={"size": 5, "color": colour}, showlegend=False))
    figure.update_layout(height=420, margin={"l": 40, "r": 10, "t": 40, "b": 40},
                         title="The bed from above: plants, flowers and their normals",
                         xaxis_title="x (m, along the bed)", yaxis_title="y (m, across)",
                         yaxis={"scaleanchor": "x", "scaleratio": 1})
    return figure


def _scores(report: dict) -> list[str]:
    run = report.get("run", {})
    parts = [f'<p class="run">flowerpose {_e(run.get("flowerpose", ""))}'
             + (f', commit {_e(run["commit"])}' if run.get("commit") else "")
             + f', {_e(run.get("date", ""))}: <code>{_e(run.get("command", ""))}</code></p>']
    header, rows, rule = table_rows(report)
    parts += ["<h2>Table I</h2>", _table(header, rows, "table-1", rule_before=rule),
              f'<p class="legend">{_e(TABLE_LEGEND)}</p>',
              "<ul>" + "".join(f"<li>{_e(line)}</li>" for line in summary_lines(report))
              + "</ul>"]
    parts += ["<h2>Errors with 95 % intervals</h2>",
              _table(*interval_rows(report["summary"]), "intervals"),
              f'<p class="legend">{_e(INTERVAL_LEGEND)}</p>']
    if report.get("compare"):
        parts += ["<h2>Compared on the same plants</h2>",
                  _table(*comparison_rows(report), "compare"),
                  f'<p class="legend">{_e(COMPARISON_LEGEND.format(name="default"))}</p>',
                  "<ul>" + "".join(f"<li>{_e(other)}: {_e(v)}</li>"
                                   for other, c in report["compare"].items()
                                   for v in c.get("paired", {}).get("verdicts", [])) + "</ul>"]
    notes = note_lines(report)
    if notes:
        parts += ["<h2>What the run assumed</h2>",
                  "<ul>" + "".join(f"<li>{_e(line)}</li>" for line in notes) + "</ul>"]
    curves = accuracy_series(report)
    if curves:
        parts.append(_figure_html(accuracy_figure(curves), "accuracy"))
    errors = {m: [e for p in report["plants"] for e in p["error_deg"][m]] for m in METHODS}
    if any(errors.values()):
        parts.append(_figure_html(_histograms(errors), "histograms"))
    if report.get("reconstruction"):
        parts += ["<h2>Reconstruction</h2>", _reconstruction_table(report["reconstruction"])]
    return parts


def _pollination(report: dict, plot: Path) -> list[str]:
    """The pollination task's results (`pollination_lines`) and its figure, where it ran:
    before and after the close look, and the time per visit."""
    if "pollination" not in report["summary"]:
        return []
    parts = ["<h2>Pollination</h2>",
             "<ul>" + "".join(f"<li>{_e(line)}</li>" for line in pollination_lines(report))
             + "</ul>"]
    if plot.is_file():
        encoded = base64.b64encode(plot.read_bytes()).decode("ascii")
        parts.append(f'<img class="views" src="data:image/png;base64,{encoded}" '
                     'alt="pollination success against the pose error, and before and after '
                     'the close look">')
    return parts


def _entry(report: dict | None, name: str) -> dict | None:
    """A plant's report.json entry (None for a detection, which has no scores)."""
    return next((p for p in (report or {}).get("plants", []) if p["plant"] == name), None)


#: What a detection is in a scored run, by its match: scored against a visible flower,
#: matched to a flower that is not scored (hidden, or on a real plant unlabelled or not in
#: the cloud), or near no flower.
SCORED, EXTRA, FALSE_POSITIVE = "scored", "extra", "false positive"


def detection_status(entry: dict, detection: int) -> str:
    """SCORED, EXTRA or FALSE_POSITIVE for a detection of a scored plant."""
    match = next((m for m in entry.get("matches", []) if m["detection"] == detection), None)
    if match is None:
        return FALSE_POSITIVE
    return SCORED if "error_deg" in match else EXTRA


def _flower_table(plant: PlantView, report: dict | None, entry: dict | None) -> str:
    """Per flower: detection id, and for a scored run what it is (scored, extra, false
    positive), its truth id, centre distance and error per method; its points and petal
    points."""
    if report is None:
        return _table(["Detection", "Plane normal", "Points", "Petal points"],
                      [[str(f.get("id", k)), _vector(f["normals"].get("plane")),
                        str(f.get("points", "")), str(f.get("petal_points", ""))]
                       for k, f in enumerate(plant.flowers)], f"flowers-{plant.name}")
    matches = {m["detection"]: m for m in (entry or {}).get("matches", [])}
    rows = []
    for k, flower in enumerate(plant.flowers):
        detection = flower.get("id", k)
        match = matches.get(detection)
        rows.append([
            str(detection), detection_status(entry or {}, detection),
            "-" if match is None else str(match["truth"]),
            "-" if match is None else f"{1000 * match['distance_m']:.1f}",
            *_errors(match),
            str(flower.get("points", "")), str(flower.get("petal_points", ""))])
    header = ["Detection", "Status", "Truth", "Distance (mm)",
              *(m.capitalize() for m in METHODS), "Points", "Petal points"]
    return _table(header, rows, f"flowers-{plant.name}")


def _errors(match: dict | None) -> list[str]:
    """A match's error per method; "-" where it has none (no match, a failed fit, or a
    flower that is matched but not scored: hidden or without a label)."""
    errors = (match or {}).get("error_deg", {})
    return ["-" if errors.get(m) is None else f"{errors[m]:.1f}°" for m in METHODS]


def _vector(value) -> str:
    return "-" if value is None else "(" + ", ".join(f"{v:.3f}" for v in value) + ")"


def _view_3d(plant: PlantView, entry: dict | None = None):
    import plotly.graph_objects as go

    points, colours = plant.cloud.points, plant.cloud.colors
    if len(points) > MAX_VIEW_POINTS:
        keep = np.random.default_rng(0).choice(len(points), MAX_VIEW_POINTS, replace=False)
        points, colours = points[keep], colours[keep]
    traces = [go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers",
                           name="cloud", hoverinfo="skip",
                           marker={"size": 1.5, "color": [f"rgb({r},{g},{b})"
                                                          for r, g, b in colours]})]
    starts, ends, labels = [], [], []
    for k, flower in enumerate(plant.flowers):
        normal = flower["normals"].get("plane")
        if normal is None:
            continue
        length = max(flower.get("box", {}).get("extent", [0.03]))
        centre = np.asarray(flower["center"], float)
        starts.append(centre)
        ends.append(centre + length * np.asarray(normal, float))
        labels.append(str(flower.get("id", k)))
    traces += _arrows(starts, ends, ESTIMATE_COLOUR, "estimated normal (plane)", labels)
    if plant.truth:
        length = float(np.median([max(f.get("box", {}).get("extent", [0.03]))
                                  for f in plant.flowers])) if plant.flowers else 0.03
        visible = [t for t in plant.truth if t.visible]
        traces += _arrows([t.center for t in visible],
                          [t.center + length * t.normal for t in visible], TRUTH_COLOUR,
                          "true normal", [str(t.id) for t in visible])
        lost = [t for t in plant.truth if not t.visible and not str(t.id).startswith("unlabelled")]
        traces += _markers([t.center for t in lost], LOST_COLOUR,
                           "labelled, not scored (hidden or not in the cloud)",
                           [f"{t.id}: not scored" for t in lost])
    if entry is not None:
        for status, colour in ((FALSE_POSITIVE, FALSE_POSITIVE_COLOUR), (EXTRA, EXTRA_COLOUR)):
            marked = [(k, f) for k, f in enumerate(plant.flowers)
                      if detection_status(entry, f.get("id", k)) == status]
            traces += _markers([f["center"] for _, f in marked], colour,
                               f"{status} ({len(marked)})",
                               [f"detection {f.get('id', k)}: {status}" for k, f in marked])
    cameras = plant.cameras is not None and len(plant.cameras) > 0
    if cameras:
        traces += _camera_path(plant.cameras)
    figure = go.Figure(traces)
    figure.update_layout(height=640, margin={"l": 0, "r": 0, "t": 30, "b": 0},
                         scene={"aspectmode": "data"}, legend={"x": 0, "y": 1},
                         title=f"{plant.name}: cloud and estimated normals (red)"
                         + (", true normals (green)" if plant.truth else "")
                         + (", camera path (blue)" if cameras else ""))
    return figure


#: How far each camera's viewing direction is drawn, metres.
CAMERA_RAY_M = 0.04


def _camera_path(cameras: np.ndarray) -> list:
    """The camera path: each frame's camera centre, joined in the order they were taken,
    and a short ray along its viewing direction (OpenCV's z axis)."""
    import plotly.graph_objects as go

    centres = cameras[:, :3, 3]
    tips = centres + CAMERA_RAY_M * cameras[:, :3, 2]
    rays: list[list[float | None]] = [[], [], []]
    for centre, tip in zip(centres, tips, strict=True):
        for axis in range(3):
            rays[axis] += [float(centre[axis]), float(tip[axis]), None]
    return [go.Scatter3d(x=centres[:, 0], y=centres[:, 1], z=centres[:, 2],
                         mode="lines+markers", name=f"camera path ({len(cameras)} frames)",
                         legendgroup="cameras", line={"color": CAMERA_COLOUR, "width": 2},
                         marker={"size": 2, "color": CAMERA_COLOUR},
                         text=[f"frame {k}" for k in range(len(cameras))], hoverinfo="text"),
            go.Scatter3d(x=rays[0], y=rays[1], z=rays[2], mode="lines", showlegend=False,
                         name="viewing directions", legendgroup="cameras",
                         line={"color": CAMERA_COLOUR, "width": 1}, hoverinfo="skip")]


def _arrows(starts, ends, colour: str, name: str, labels: list[str]) -> list:
    """One line trace for all the segments, and their labels at the tips."""
    import plotly.graph_objects as go

    if not starts:
        return []
    xyz: list[list[float | None]] = [[], [], []]
    for start, end in zip(starts, ends, strict=True):
        for axis in range(3):
            xyz[axis] += [float(start[axis]), float(end[axis]), None]
    tips = np.asarray(ends, float)
    return [go.Scatter3d(x=xyz[0], y=xyz[1], z=xyz[2], mode="lines", name=name,
                         line={"color": colour, "width": 6}, hoverinfo="skip"),
            go.Scatter3d(x=tips[:, 0], y=tips[:, 1], z=tips[:, 2], mode="text", text=labels,
                         textfont={"color": colour}, showlegend=False, hoverinfo="text")]


def _markers(centres, colour: str, name: str, labels: list[str]) -> list:
    """Open circles round flower centres, named in the legend, each labelled on hover."""
    import plotly.graph_objects as go

    if not len(centres):
        return []
    at = np.asarray(centres, float).reshape(-1, 3)
    return [go.Scatter3d(x=at[:, 0], y=at[:, 1], z=at[:, 2], mode="markers", name=name,
                         text=labels, hoverinfo="text",
                         marker={"size": 9, "color": colour, "symbol": "circle-open",
                                 "line": {"width": 3, "color": colour}})]


def accuracy_series(report: dict) -> dict[str, dict]:
    """The accuracy curves a report holds, by label: each fit of this run and, for each
    compared setting or method, its plane fit's."""
    series = {f"{fit}": report["summary"]["accuracy"][fit] for fit in METHODS
              if report["summary"].get("accuracy", {}).get(fit, {}).get("share") is not None}
    for name, compared in report.get("compare", {}).items():
        curve = compared["summary"].get("accuracy", {}).get("plane", {})
        if curve.get("share") is not None:
            series[f"{name}: plane"] = curve
    return series


def accuracy_figure(series: dict[str, dict]):
    """The accuracy curves on one plot: the share of flowers within each angle."""
    import plotly.graph_objects as go

    figure = go.Figure([go.Scatter(x=[0, *curve["thresholds_deg"]], y=[0.0, *curve["share"]],
                                   mode="lines+markers",
                                   name=f"{label} (AUC {curve['auc']:.3f}, {curve['n']} flowers)")
                        for label, curve in series.items()])
    figure.update_layout(height=360, title="Accuracy: share of visible flowers within each "
                         "angle (a missed flower fails at every angle)",
                         xaxis_title="angle error threshold (degrees)",
                         yaxis_title="share of flowers", yaxis_range=[0, 1.02],
                         margin={"l": 40, "r": 10, "t": 40, "b": 40})
    return figure


def _histograms(errors: dict[str, list[float]]):
    import plotly.graph_objects as go

    figure = go.Figure([go.Histogram(x=values, name=method, opacity=0.6,
                                     xbins={"start": 0, "size": 1})
                        for method, values in errors.items() if values])
    figure.update_layout(barmode="overlay", height=320, title="Normal errors (degrees)",
                         xaxis_title="error (degrees)", yaxis_title="flowers",
                         margin={"l": 40, "r": 10, "t": 40, "b": 40})
    return figure


def _reconstruction_table(reconstruction: dict) -> str:
    rows = [[plant, key, json.dumps(value) if isinstance(value, dict | list) else str(value)]
            for plant, metrics in reconstruction.items()
            for key, value in (metrics.items() if isinstance(metrics, dict) else [])]
    return _table(["Plant", "Metric", "Value"], rows, "reconstruction")


def _figure_html(figure, div_id: str) -> str:
    """The figure's div and script; plotly's JavaScript is in the page's head, once."""
    import plotly.io as pio

    return pio.to_html(figure, include_plotlyjs=False, full_html=False, div_id=div_id,
                       config={"displaylogo": False})


def _table(header: list[str], rows: list[list[str]], table_id: str,
           rule_before: int | None = None) -> str:
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join(
        f'<tr{" class=rule" if k == rule_before else ""}>'
        + "".join(f"<td>{_e(c)}</td>" for c in row) + "</tr>" for k, row in enumerate(rows))
    return f'<table id="{_e(table_id)}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _e(text: object) -> str:
    return html.escape(str(text))


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<script type="text/javascript">{plotly}</script>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1200px; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1em; }}
th, td {{ border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: right; }}
th {{ background: #eee; }} td:first-child {{ text-align: left; }}
tr.rule td {{ border-top: 3px double #555; }}
.legend, .run {{ color: #444; font-size: 0.9em; }}
img.views {{ max-width: 100%; }}
</style></head><body>
{body}
</body></html>
"""
