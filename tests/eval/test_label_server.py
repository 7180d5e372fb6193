"""`flowerpose label`: the page's server on a small real-plant folder (its detections as
proposals, a snap to the points, a save that keeps the earlier file), the page itself in
headless Chromium, and every request not from the page refused: another origin, another
host name (DNS rebinding), a POST without the session's token or not JSON."""

import http.client
import json
import shutil
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest
from realplants import CENTRES, NORMALS, write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.labelling import label_server
from flowerpose.eval.scoring.labels import read_labels
from flowerpose.eval.scoring.real_source import read_real_plant, real_truth
from flowerpose.jsonio import write_json


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1, 1))))


def _serve(tmp_path, detected: int):
    """A plant folder with a cloud and flowers.json detections of its first `detected`
    flowers (each normal 20 degrees off), served on a free port: (folder, url, server)."""
    folder = write_real_plant(tmp_path / "plant", "cloud")
    (folder / "labels.json").unlink()
    tilted = NORMALS + 0.35 * np.cross(NORMALS, [0.0, 0.0, 1.0])
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    write_json(folder / "flowers.json", {"units": "m", "flowers": [
        {"id": k, "center": c.tolist(), "normals": {"plane": n.tolist()}}
        for k, (c, n) in enumerate(zip(CENTRES[:detected], tilted[:detected], strict=True))]})
    session = label_server.open_session(folder, "tester", "m")
    server = label_server.make_server(session)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}"
    TOKENS[url] = server.token
    return folder, url, server


#: Each served page's token, by its address: what the page's own requests carry.
TOKENS: dict[str, str] = {}


@pytest.fixture
def served(tmp_path):
    folder, url, server = _serve(tmp_path, detected=4)
    yield folder, url
    server.shutdown()
    server.server_close()


def _get(url: str):
    with urllib.request.urlopen(url, timeout=30) as answer:
        return answer.read()


def _post(url: str, body: dict) -> tuple[int, dict]:
    """A POST as the page sends it: JSON, with its session's token."""
    base = url.rsplit("/", 1)[0]
    request = urllib.request.Request(url, json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json",
                                              label_server.TOKEN_HEADER: TOKENS[base]})
    try:
        with urllib.request.urlopen(request, timeout=30) as answer:
            return answer.status, json.loads(answer.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


def test_the_page_loads_nothing_from_the_internet(served):
    _, url = served
    page = _get(url + "/").decode()
    assert "Plotly" in page and "/*PLOTLY*/" not in page
    assert 'src="http' not in page and "<link" not in page


def test_the_detections_come_as_proposals_and_a_snap_finds_the_flowers_plane(served):
    folder, url = served
    state = json.loads(_get(url + "/state"))
    assert state["points"] == state["shown"] == len(state["x"]) > 1000
    assert [f["state"] for f in state["flowers"]] == ["proposed"] * 4
    assert state["started_from"] == f"{folder / 'flowers.json'} (detections)"
    proposal = state["flowers"][1]
    assert _angle(proposal["normal"], NORMALS[1]) > 15  # the detection is off
    status, fit = _post(url + "/fit", {"center": proposal["center"],
                                       "towards": proposal["normal"]})
    assert status == 200 and fit["points"] >= label_server.MIN_FIT_POINTS
    assert _angle(fit["normal"], NORMALS[1]) < 8  # snapped onto the corolla's plane


def test_a_save_writes_labels_eval_reads_and_keeps_the_earlier_file(served):
    folder, url = served
    flowers = json.loads(_get(url + "/state"))["flowers"]
    flowers[0].update(state="labelled", normal=NORMALS[0].tolist())
    flowers[1].update(state="unlabelled")
    flowers[2].update(state="rejected")  # flowers[3] stays a proposal nobody judged
    status, saved = _post(url + "/save", {"flowers": flowers,
                                          "session": {"seconds": 42, "actions": {"accept": 1}}})
    assert status == 200 and saved["undecided"] == 1 and saved["backup"] is None
    assert saved["counts"] == {"labelled": 1, "unlabelled": 1, "rejected": 1}
    labels = read_labels(folder / "labels.json")
    assert [f.state for f in labels.flowers] == ["labelled", "unlabelled", "rejected"]
    assert labels.sessions[-1]["labeller"] == "tester" and labels.sessions[-1]["seconds"] == 42
    truth = real_truth(read_real_plant(folder))
    assert [t.id for t in truth if t.visible] == ["d0"]
    status, again = _post(url + "/save", {"flowers": flowers})
    assert status == 200 and again["backup"].endswith("labels.json.1.bak")
    assert len(read_labels(folder / "labels.json").sessions) == 2


def test_a_bad_save_is_refused_and_writes_nothing(served):
    folder, url = served
    status, answer = _post(url + "/save", {"flowers": [{"id": "x", "center": [0, 0, 0.3],
                                                        "normal": None, "state": "labelled"}]})
    assert status == 400 and "without a normal" in answer["error"]
    status, answer = _post(url + "/save", {"flowers": "none"})
    assert status == 400
    assert not (folder / "labels.json").exists()


def _raw(url: str, method: str, path: str, body: bytes = b"", **headers) -> tuple[int, dict]:
    """A request with the headers given as they are (`Host` too): what another page, or a
    name rebound to 127.0.0.1, would send."""
    port = int(url.rsplit(":", 1)[1])
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.putrequest(method, path, skip_host="Host" in headers)
    for name, value in {**headers, "Content-Length": str(len(body))}.items():
        connection.putheader(name.replace("_", "-"), value)
    connection.endheaders(body)
    answer = connection.getresponse()
    status, data = answer.status, answer.read()
    connection.close()
    return status, json.loads(data) if data.startswith(b"{") else {}


def test_requests_from_anything_but_the_page_are_refused_and_change_nothing(served):
    folder, url = served
    status, _ = _post(url + "/save", {"flowers": [], "session": {}})
    assert status == 200
    saved = (folder / "labels.json").read_bytes()
    token = TOKENS[url]
    empty = json.dumps({"flowers": [], "session": {"who": "evil"}}).encode()
    host = url.removeprefix("http://")
    for headers in (
            # Any web page may send this without asking: another origin, plain text.
            {"Origin": "http://evil.example", "Content-Type": "text/plain"},
            # Not even with the token: still another origin.
            {"Origin": "http://evil.example", "Content-Type": "application/json",
             "X_Flowerpose_Token": token},
            # From the page's origin, but plain text, or without the token.
            {"Origin": f"http://{host}", "Content-Type": "text/plain",
             "X_Flowerpose_Token": token},
            {"Origin": f"http://{host}", "Content-Type": "application/json"},
            # A name rebound to 127.0.0.1.
            {"Host": f"evil.example:{host.split(':')[1]}", "Content-Type": "application/json",
             "X_Flowerpose_Token": token}):
        status, data = _raw(url, "POST", "/save", empty, **headers)
        assert status == 403 and data["error"], headers
    assert (folder / "labels.json").read_bytes() == saved
    assert not list(folder.glob("labels.json.*"))  # no backup of a refused save
    # DNS rebinding cannot read the cloud; the server's own names can.
    assert _raw(url, "GET", "/state", Host=f"evil.example:{host.split(':')[1]}")[0] == 403
    assert _raw(url, "GET", "/state", Host=f"localhost:{host.split(':')[1]}")[0] == 200
    # The page carries the token that opens its POSTs.
    assert json.dumps(token).encode() in _get(url + "/")
    assert _raw(url, "POST", "/save", b"[]", Content_Type="application/json",
                X_Flowerpose_Token=token)[0] == 400


def test_a_large_cloud_is_drawn_decimated(served, monkeypatch):
    folder, _ = served
    monkeypatch.setattr(label_server, "MAX_SHOWN_POINTS", 500)
    session = label_server.open_session(folder, "tester", "m")
    shown = label_server.shown_points(session)
    assert len(shown) == 500 and len(np.unique(shown)) == 500
    assert len(session.cloud) > 500  # what labels refer to stays whole


def test_a_folder_without_points_is_one_line(tmp_path, capsys):
    assert main(["label", str(tmp_path / "missing"), "--no-browser"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no such folder" in err and err.count("\n") == 0
    (tmp_path / "empty").mkdir()
    assert main(["label", str(tmp_path / "empty"), "--no-browser"]) == 2
    assert "no cloud.ply" in capsys.readouterr().err


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed")
def test_a_labeller_in_a_browser_accepts_moves_turns_adds_and_saves(tmp_path, capsys):
    """The page in the system Chromium (Playwright, no browser download), no request
    leaving 127.0.0.1: two detections accepted, one moved and turned, the flower the
    pipeline missed added, saved; the file says so and eval scores it."""
    sync_api = pytest.importorskip("playwright.sync_api")
    folder, url, server = _serve(tmp_path, detected=3)
    requests: list[str] = []
    moved_to = (CENTRES[2] + [0.002, -0.001, 0.0]).tolist()
    turned = NORMALS[2]
    azimuth = round(float(np.degrees(np.arctan2(turned[1], turned[0]))))
    elevation = round(float(np.degrees(np.arcsin(turned[2]))))
    try:
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"])
            page = browser.new_page()
            page.on("request", lambda request: requests.append(request.url))
            page.goto(url + "/")
            page.wait_for_selector("#list tbody tr >> nth=2")
            assert page.locator(".state-proposed").count() == 3
            page.keyboard.press("a")  # the first row is selected: accept it
            page.keyboard.press("a")  # then the next
            page.locator("#list tbody tr").nth(2).click()
            page.keyboard.press("m")  # move: the next click on the cloud is the centre
            page.evaluate("at => document.getElementById('view').emit('plotly_click', "
                          "{points: [{x: at[0], y: at[1], z: at[2], curveNumber: 0}]})",
                          moved_to)
            page.wait_for_function("() => document.getElementById('status').textContent"
                                   ".includes('moved')")
            page.evaluate("([a, e]) => { document.getElementById('azimuth').value = a; "
                          "const el = document.getElementById('elevation'); el.value = e; "
                          "el.dispatchEvent(new Event('change')); }", [azimuth, elevation])
            page.keyboard.press("a")
            page.keyboard.press("n")  # add: the flower the pipeline missed
            page.evaluate("at => document.getElementById('view').emit('plotly_click', "
                          "{points: [{x: at[0], y: at[1], z: at[2], curveNumber: 0}]})",
                          CENTRES[3].tolist())
            page.wait_for_function("() => document.getElementById('status').textContent"
                                   ".includes('added')")
            page.keyboard.press("Control+s")
            page.wait_for_function("() => document.getElementById('status').textContent"
                                   ".startsWith('saved')")
            said = page.locator("#status").text_content()
            browser.close()
    finally:
        server.shutdown()
        server.server_close()
    assert requests and all(u.startswith("http://127.0.0.1:") for u in requests), requests
    assert "4 labelled" in said and "actions this session" in said
    labels = read_labels(folder / "labels.json")
    by_id = {f.id: f for f in labels.flowers}
    assert [f.state for f in labels.flowers] == ["labelled"] * 4
    assert np.allclose(by_id["d2"].center, moved_to)
    expected = [np.cos(np.radians(elevation)) * np.cos(np.radians(azimuth)),
                np.cos(np.radians(elevation)) * np.sin(np.radians(azimuth)),
                np.sin(np.radians(elevation))]
    assert _angle(by_id["d2"].normal, expected) < 0.01
    added = next(f for f in labels.flowers if f.id.startswith("new"))
    assert np.allclose(added.center, CENTRES[3]) and added.normal is not None
    actions = labels.sessions[-1]["actions"]
    assert actions["accept"] == 3 and actions["move"] == 1 and actions["add"] == 1
    assert actions["turn"] == 1 and labels.sessions[-1]["seconds"] >= 0
    assert main(["eval", "--source", "real", str(folder), "--out", str(tmp_path / "run"),
                 "-q"]) == 0
    capsys.readouterr()
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["plants"][0]["visible"] == 4 and report["plants"][0]["found_visible"] >= 3


def test_a_port_out_of_range_or_taken_is_one_line(tmp_path, capsys):
    folder = write_real_plant(tmp_path / "plant", "cloud")
    with pytest.raises(SystemExit) as refused:
        main(["label", str(folder), "--port", "70000", "--no-browser"])
    assert refused.value.code == 2
    assert "at most 65,535 (a TCP port)" in capsys.readouterr().err
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["label", str(folder), "--port", str(port), "--no-browser"]) == 2
    assert "cannot serve there" in capsys.readouterr().err


def test_labels_saved_from_a_sagemaker_folder_read_back_the_same(tmp_path):
    """The authors' folders carry SageMaker labels at x25 with "truth_scale": 25 in their
    source.json; a save writes this project's file (its own scale 1), and opening it again
    or scoring it applies that scale once, not source.json's on top."""
    folder = write_real_plant(tmp_path / "plant", "cloud", source={"truth_scale": 25})
    before = real_truth(read_real_plant(folder))
    session = label_server.open_session(folder, "tester", "m")
    flowers = [{**f, "state": "labelled"} for f in session.start]
    label_server.save_labels(session, {"flowers": flowers})
    again = label_server.open_session(folder, "tester", "m")
    assert np.allclose([f["center"] for f in again.start],
                       [f["center"] for f in session.start])
    after = real_truth(read_real_plant(folder))
    assert np.allclose([t.center for t in after], [t.center for t in before])
    assert sum(t.visible for t in after) == sum(t.visible for t in before) == len(CENTRES)
    with pytest.raises(InputError, match="contradicts"):
        read_real_plant(folder, truth_scale=25)


def test_a_save_that_would_not_read_back_is_refused_and_writes_nothing(served):
    folder, url = served
    flowers = json.loads(_get(url + "/state"))["flowers"]
    twice = [{**flowers[0], "state": "labelled", "normal": [0, 0, 1]},
             {**flowers[0], "state": "labelled", "normal": [0, 0, 1]}]
    status, answer = _post(url + "/save", {"flowers": twice})
    assert status == 400 and "given 2 times" in answer["error"]
    zero = [{**flowers[0], "state": "labelled", "normal": [0, 0, 0]}]
    status, answer = _post(url + "/save", {"flowers": zero})
    assert status == 400 and "flower d0" in answer["error"] and "normal" in answer["error"]
    assert not (folder / "labels.json").exists() and not list(folder.glob("*.bak"))
    # A hand-written "units" is refused, not read as metres without a word.
    (folder / "labels.json").write_text(json.dumps({
        "format": "flowerpose-labels", "version": 1, "units": "mm", "flowers": []}))
    with pytest.raises(InputError, match="unknown key 'units'"):
        read_labels(folder / "labels.json")
