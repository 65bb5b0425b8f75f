"""The HTML pages in-process: real values against the JSON API, errors as HTML, no external URLs, SVG geometry."""

from __future__ import annotations

import json
import math
import re
from html.parser import HTMLParser
from typing import Any

import pytest
from server_helpers import app_client, golden_bytes, upload

from kitti_eval.cli import main as cli_main
from kitti_eval.demo import demo_paths
from kitti_eval_server.web import STATIC_DIR
from kitti_eval_server.web.svg import Plot, bev_corners, bev_view, pr_chart

DEMO_PRED = demo_paths()[1].read_bytes()
DIFFS = ("easy", "moderate", "hard")


class Page(HTMLParser):
    """What the tests look at in a page: cells with ``data-key``, links and sources, polylines, text."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.cells: dict[str, dict[str, Any]] = {}  # data-key -> {"value", "class", "text"}
        self.urls: list[str] = []
        self.polylines: list[dict[str, str]] = []
        self.svgs = 0
        self.tags: list[tuple[str, dict[str, str]]] = []
        self.scopes: list[str | None] = []  # per tag: the data-evaluation of the figure/section it is in
        self._scope: str | None = None
        self._open: list[str] = []  # data-keys of the cells being read
        self.text: list[str] = []
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag in ("figure", "section"):
            self._scope = a.get("data-evaluation")
        self.tags.append((tag, a))
        self.scopes.append(self._scope)
        self.urls += [a[k] for k in ("src", "href", "action") if k in a]
        if tag == "svg":
            self.svgs += 1
        if tag == "polyline":
            self.polylines.append(a)
        if "data-key" in a:
            assert a["data-key"] not in self.cells, f"duplicate data-key {a['data-key']}"
            self.cells[a["data-key"]] = {"value": a.get("data-value"), "class": a.get("class", ""), "text": ""}
            self._open.append(a["data-key"])

    def handle_endtag(self, tag: str) -> None:
        if tag in ("figure", "section"):
            self._scope = None
        if tag == "td" and self._open:
            self._open.pop()

    def handle_data(self, data: str) -> None:
        self.text.append(data)
        if self._open:
            self.cells[self._open[-1]]["text"] += data.strip()

    def classes(self, tag: str, first: str, scope: str | None = None) -> list[list[str]]:
        """The other classes of each ``tag`` whose class list starts with ``first`` (in ``scope`` if given)."""
        return [
            a["class"].split()[1:]
            for (t, a), sc in zip(self.tags, self.scopes)
            if t == tag and a.get("class", "").split()[:1] == [first] and (scope is None or sc == scope)
        ]

    def all_text(self) -> str:
        return " ".join(t.strip() for t in self.text if t.strip())


def ap_values(doc: dict[str, Any]) -> dict[str, float | None]:
    """``"<set>/<recall>/<class>/<metric>/<difficulty>" -> value`` of a JSON document's ``ap``."""
    return {
        f"{s}/{r}/{c}/{m}/{d}": v
        for s, by_recall in doc["ap"].items()
        for r, by_class in by_recall.items()
        for c, by_metric in by_class.items()
        for m, by_diff in by_metric.items()
        for d, v in by_diff.items()
    }


def printed(value: float | None, metric: str, sign: bool = False) -> str:
    """An AP with the decimals of the CLI's table (``kitti-eval --format table``): 2 for AOS, 4 otherwise."""
    if value is None:
        return "-"
    return f"{value:{'+' if sign else ''}.{2 if metric == 'aos' else 4}f}"


def cli_table(text: str, doc: dict[str, Any]) -> dict[str, str]:
    """``"<set>/<recall>/<class>/<metric>/<difficulty>" -> value`` as ``kitti-eval --format table`` prints it
    (``-`` where it prints ``n/a``); its blocks come per class, threshold set, then R11 and R40."""
    blocks = iter((c, s, r) for c in doc["classes"] for s in doc["threshold_sets"] for r in ("R11", "R40"))
    out = {}
    for line in text.splitlines():
        if line.endswith(":"):
            cls, oset, recall = next(blocks)
            assert line.startswith(f"{cls} {'AP' if recall == 'R11' else 'AP_R40'}@"), line
            continue
        metric, values = line.split("AP:")
        for d, v in zip(DIFFS, values.split(", "), strict=True):
            out[f"{oset}/{recall}/{cls}/{metric.strip()}/{d}"] = "-" if v == "n/a" else v
    return out


def legends(html: str) -> dict[str, str]:
    """``"<set>/R40/<class>/<metric>/<difficulty>" -> the AP`` in the legends of the precision-recall charts."""
    out = {}
    for block in html.split('<details class="curves"')[1:]:
        oset = re.search(r"<summary>(\S+) IoU thresholds", block).group(1)
        for figure in block.split('<figure class="chart">')[1:]:
            cls, metric = re.search(r"<figcaption>(\S+) (\S+)</figcaption>", figure).groups()
            for d, text in re.findall(r'<span class="legend (\w+)">\w+ ([^<]*)</span>', figure):
                out[f"{oset}/R40/{cls}/{metric}/{d}"] = text
    return out


def submit(client: Any, data: bytes = DEMO_PRED, filename: str = "result.pkl.gz", **fields: str) -> Any:
    form = {"gt": "demo", "protocol": "official", **fields}
    return client.post("/ui/evaluations", data=form, files={"predictions": (filename, data)}, follow_redirects=False)


def evaluation_id(response: Any) -> str:
    assert response.status_code == 303, response.text
    location = response.headers["location"]
    assert location.startswith("/evaluations/")
    return location.rsplit("/", 1)[-1]


def assert_html_error(response: Any, status: int, *needles: str) -> Page:
    assert response.status_code == status, (response.status_code, response.text[:500])
    assert response.headers["content-type"].startswith("text/html")
    assert "Traceback" not in response.text and 'File "' not in response.text
    page = Page(response.text)
    text = page.all_text()
    for needle in needles:
        assert needle in text, (needle, text[:2000])
    return page


@pytest.fixture(scope="module")
def two(client) -> tuple[str, str]:
    """Two evaluations of the demo: the bundled predictions (official) and the golden ones (openpcdet)."""
    first = evaluation_id(submit(client, model="pointpillars"))
    second = evaluation_id(
        submit(client, golden_bytes("result.pkl"), "result.pkl", protocol="openpcdet", model="second")
    )
    return first, second


# ------------------------------------------------------------------------------------------------- home


def test_home_has_the_upload_form_and_the_ground_truths(client) -> None:
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    page = Page(r.text)
    forms = [a for t, a in page.tags if t == "form" and a.get("action") == "/ui/evaluations"]
    assert forms and forms[0]["method"] == "post" and forms[0]["enctype"] == "multipart/form-data"
    assert ("input", {"type": "file", "name": "predictions", "id": "predictions", "required": ""}) in page.tags
    options = [a["value"] for t, a in page.tags if t == "option"]
    assert "demo" in options and {"official", "openpcdet"} <= set(options)
    assert any(t == "input" and a.get("name") == "model" for t, a in page.tags)


def test_history_lists_evaluations_newest_first_with_the_summary(client, two) -> None:
    first, second = two
    page = Page(client.get("/").text)
    boxes = [a["value"] for t, a in page.tags if t == "input" and a.get("type") == "checkbox"]
    assert boxes.index(second) < boxes.index(first)
    assert f"/evaluations/{first}" in page.urls
    summary = client.get(f"/v1/evaluations/{first}").json()["ap"]["strict"]["R40"]
    text = page.all_text()
    for cls in ("Car", "Pedestrian", "Cyclist"):
        assert printed(summary[cls]["3d"]["moderate"], "3d") in text  # four decimals, as the CLI's 3d row
    assert "pointpillars" in text and "second" in text
    history = next(a for t, a in page.tags if t == "form" and a.get("id") == "history")
    assert history["action"] == "/compare" and history["method"] == "get"  # Compare works without JavaScript too


def history_row(html: str, evaluation: str) -> str:
    """The HTML of the history's row for one evaluation."""
    return html.split(f'<tr data-id="{evaluation}"', 1)[1].split("</tr>", 1)[0]


def test_history_header_says_which_ap_it_shows(client, two) -> None:
    html = client.get("/").text
    head = html.split('<table class="history">', 1)[1].split("</thead>", 1)[0]
    text = " ".join(re.sub(r"<[^>]+>", " ", head).split())  # what is shown, not the tooltips
    assert "Moderate 3D AP (R40, strict IoU)" in text
    assert text.endswith("Car Pedestrian Cyclist")  # the classes under it


def test_history_dates_do_not_wrap(client, two) -> None:
    html = client.get("/").text
    for evaluation in two:
        assert re.match(
            r'[^>]*>\s*<td><input[^>]*></td>\s*<td class="created"><a [^>]*>[0-9-]+ [0-9:]+</a>',
            history_row(html, evaluation),
        )
    assert css_rules()["table.history td.created"]["white-space"] == "nowrap"


def test_history_shows_every_label_even_a_lone_one(client) -> None:
    main, feature = (
        upload(client, DEMO_PRED, "result.pkl.gz", fields={"label": f"branch={b}"}).json()["id"]
        for b in ("main", "feature")
    )
    tagged = upload(client, DEMO_PRED, "result.pkl.gz", fields={"model": "pp", "label": ["branch=main", "seed=3"]})
    html = client.get("/").text
    tags = {eid: re.findall(r'<span class="tag">([^<]*)</span>', history_row(html, eid)) for eid in (main, feature)}
    assert tags == {main: ["branch=main"], feature: ["branch=feature"]}
    row = history_row(html, tagged.json()["id"])
    assert sorted(re.findall(r'<span class="tag">([^<]*)</span>', row)) == ["branch=main", "model=pp", "seed=3"]


# ------------------------------------------------------------------------------------------- evaluation


def test_evaluation_page_values_equal_the_json(client, two) -> None:
    first, _ = two
    doc = client.get(f"/v1/evaluations/{first}").json()
    r = client.get(f"/evaluations/{first}")
    assert r.status_code == 200
    page = Page(r.text)
    expected = ap_values(doc)
    assert set(page.cells) == set(expected)
    assert len(expected) == 2 * 2 * 3 * 4 * 3  # sets × recalls × classes × metrics × difficulties
    for key, value in expected.items():
        cell = page.cells[key]
        if value is None:
            assert cell["value"] == "" and cell["text"] == "-", key
        else:
            assert float(cell["value"]) == value, key
            assert cell["text"] == printed(value, key.split("/")[3]), key
    text = page.all_text()
    assert "result.pkl.gz" in text and "model=pointpillars" in text and "official" in text
    assert f"/v1/evaluations/{first}" in page.urls


def test_the_demo_uploaded_on_the_page_reads_as_the_cli_prints_it(client, two, tmp_path) -> None:
    first, _ = two  # the bundled demo predictions against the demo ground truth, official protocol
    out = tmp_path / "demo.json"
    assert cli_main(["demo", "--format", "json", "--output", str(out), "--quiet"]) == 0
    cli_doc = json.loads(out.read_text())
    assert cli_main(["demo", "--format", "table", "--output", str(tmp_path / "demo.txt"), "--quiet"]) == 0
    table = cli_table((tmp_path / "demo.txt").read_text(), cli_doc)
    page = Page(client.get(f"/evaluations/{first}").text)
    expected = ap_values(cli_doc)
    assert set(page.cells) == set(expected) == set(table)
    assert {key: cell["text"] for key, cell in page.cells.items()} == table  # AOS with 2 decimals, the rest 4
    in_legends = legends(client.get(f"/evaluations/{first}").text)
    assert len(in_legends) == 2 * 3 * 4 * 3 and in_legends == {k: table[k] for k in in_legends}
    for key, value in expected.items():
        assert table[key] == printed(value, key.split("/")[3]), key
        assert page.cells[key]["value"] == ("" if value is None else repr(value)), key


def test_evaluation_page_draws_the_curves(client, two) -> None:
    first, _ = two
    page = Page(client.get(f"/evaluations/{first}").text)
    curves = [p for p in page.polylines if "curve" in p.get("class", "").split()]
    assert len(curves) == 2 * 3 * 4 * 3  # sets × classes × metrics × difficulties
    assert {p["data-difficulty"] for p in curves} == set(DIFFS)
    plot = Plot()
    for p in curves:
        points = [tuple(map(float, xy.split(","))) for xy in p["points"].split()]
        assert len(points) == 41
        assert points[0][0] == pytest.approx(plot.x0) and points[-1][0] == pytest.approx(plot.x1)
        assert all(plot.y1 - 1e-6 <= y <= plot.y0 + 1e-6 for _, y in points)


def test_evaluation_without_curves_says_so(client) -> None:
    r = upload(client, DEMO_PRED, "result.pkl.gz")
    assert r.status_code == 201
    page = Page(client.get(f"/evaluations/{r.json()['id']}").text)
    assert "No curves stored" in page.all_text()
    assert not page.polylines
    assert len(page.cells) == 144


def test_unknown_evaluation_is_an_html_404(client) -> None:
    assert_html_error(client.get("/evaluations/no-such-id"), 404, "no evaluation with id 'no-such-id'")


# ---------------------------------------------------------------------------------------------- compare


def test_compare_shows_b_minus_a_with_colours_and_notes(client, two) -> None:
    first, second = two
    a = client.get(f"/v1/evaluations/{first}").json()
    b = client.get(f"/v1/evaluations/{second}").json()
    r = client.get("/compare", params={"a": first, "b": second})
    assert r.status_code == 200
    page = Page(r.text)
    va, vb = ap_values(a), ap_values(b)
    assert set(page.cells) == set(va) & set(vb)
    coloured = set()
    for key, cell in page.cells.items():
        if va[key] is None or vb[key] is None:
            assert cell["value"] == "" and cell["text"] == "-"
            continue
        delta = vb[key] - va[key]
        assert float(cell["value"]) == delta, key
        assert cell["text"] == printed(delta, key.split("/")[3], sign=True), key
        kind = "pos" if delta > 0 else "neg" if delta < 0 else "zero"
        assert cell["class"].split() == ["num", "delta", kind], key
        coloured.add(kind)
    assert {"pos", "neg"} & coloured
    side = r'<td class="num side">([^<]*)</td>'
    sides = re.findall(side + side + r'\s*<td class="num [^"]*" data-key="([^"]+)"', r.text)
    assert len(sides) == len(page.cells)
    for a_text, b_text, key in sides:  # A and B as the CLI's table prints them
        assert (a_text, b_text) == (printed(va[key], key.split("/")[3]), printed(vb[key], key.split("/")[3])), key
    text = page.all_text()
    assert "different protocols: official and openpcdet" in text
    assert "the evaluations used different ground truth" not in text


def test_compare_without_javascript_orders_by_time(client, two) -> None:
    first, second = two
    r = client.get("/compare", params=[("e", second), ("e", first)])
    assert r.status_code == 200
    plain = Page(client.get("/compare", params={"a": first, "b": second}).text)
    assert Page(r.text).cells == plain.cells


def test_compare_errors_are_html(client, two) -> None:
    first, _ = two
    assert_html_error(client.get("/compare", params={"a": first, "b": "nope"}), 404, "no evaluation with id 'nope'")
    assert_html_error(client.get("/compare", params={"a": first}), 422, "compare needs two evaluations")


# ----------------------------------------------------------------------------------------------- upload


def test_upload_redirects_to_the_new_evaluation(client) -> None:
    eid = evaluation_id(submit(client, model="redirected"))
    body = client.get(f"/v1/evaluations/{eid}").json()
    assert body["evaluation"]["labels"] == {"model": "redirected"}
    assert body["protocol"] == "official" and body["frames"] == 200 and "curves" in body


@pytest.mark.parametrize(
    ("files", "fields", "status", "needle"),
    [
        ({"predictions": ("x.pkl", b"not a pickle")}, {"gt": "demo"}, 422, "x.pkl: unknown format"),
        ({"predictions": ("result.pkl.gz", DEMO_PRED)}, {"gt": "nope"}, 404, "no ground truth named 'nope'"),
        ({"predictions": ("", b"")}, {"gt": "demo"}, 422, "choose a predictions file"),
        (None, {"gt": "demo"}, 422, "choose a predictions file"),
        (
            {"predictions": ("result.pkl.gz", DEMO_PRED)},
            {"gt": "demo", "protocol": "nuscenes"},
            422,
            "unknown protocol 'nuscenes'",
        ),
        ({"predictions": ("result.pkl.gz", DEMO_PRED)}, {"gt": "demo", "model": "x" * 300}, 422, "at most 256"),
    ],
)
def test_bad_uploads_render_the_home_page_with_the_error(client, files, fields, status, needle) -> None:
    if files is None:
        r = client.post("/ui/evaluations", data=fields, follow_redirects=False)
    else:
        r = client.post("/ui/evaluations", data=fields, files=files, follow_redirects=False)
    page = assert_html_error(r, status, needle)
    assert any(t == "form" and a.get("action") == "/ui/evaluations" for t, a in page.tags)
    errors = [a for t, a in page.tags if t == "p" and a.get("class") == "error"]
    assert len(errors) == 1


def test_the_upload_cap_applies_to_the_form(tmp_path) -> None:
    with app_client(tmp_path / "data", max_upload_mb=0.05) as c:
        big = DEMO_PRED  # 180 kB > 50 kB
        assert submit(c, big).status_code == 413  # declared length: refused before the body is read

        boundary = "kitti-eval-boundary"
        body = (
            (
                f'--{boundary}\r\nContent-Disposition: form-data; name="gt"\r\n\r\ndemo\r\n'
                f'--{boundary}\r\nContent-Disposition: form-data; name="predictions"; filename="r.pkl.gz"\r\n'
                f"Content-Type: application/octet-stream\r\n\r\n"
            ).encode()
            + big
            + f"\r\n--{boundary}--\r\n".encode()
        )

        def chunks():
            for i in range(0, len(body), 8192):
                yield body[i : i + 8192]

        r = c.post(
            "/ui/evaluations", content=chunks(), headers={"Content-Type": f"multipart/form-data; boundary={boundary}"}
        )
        assert_html_error(r, 413, "larger than the upload limit")


# ----------------------------------------------------------------------------------------------- frames


def frame_rows(page: Page) -> list[dict[str, Any]]:
    """The links of the worst-frames table: frame id and href."""
    links = [a["href"] for t, a in page.tags if t == "a" and a.get("href", "").startswith("/frames/")]
    return [{"frame": href.split("?")[0].rsplit("/", 1)[-1], "href": href} for href in links]


def worst_table(html: str) -> list[list[str]]:
    """The worst-frames table's cells as text, row by row."""
    body = html.split('<table class="frames">', 1)[1].split("</table>", 1)[0]
    rows = re.findall(r"<tr>(.*?)</tr>", body, flags=re.S)[1:]
    return [
        [re.sub(r"<[^>]+>", "", c).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", r, flags=re.S)] for r in rows
    ]


def test_worst_frames_equal_the_json_and_link_to_the_frame_view(client, two) -> None:
    first, _ = two
    expected = client.get(f"/v1/evaluations/{first}/frames").json()["frames"]
    html = client.get(f"/evaluations/{first}").text
    assert worst_table(html) == [[f["frame"], str(f["tp"]), str(f["fp"]), str(f["fn"])] for f in expected]
    rows = frame_rows(Page(html))
    assert [r["frame"] for r in rows] == [f["frame"] for f in expected] and len(rows) == 20
    assert rows[0]["href"] == (
        f"/frames/{expected[0]['frame']}?e={first}&cls=Car&metric=3d&difficulty=moderate&set=strict"
    )


def test_worst_frames_follow_the_selectors(client, two) -> None:
    first, _ = two
    params = {"cls": "Pedestrian", "metric": "bev", "difficulty": "hard", "set": "loose"}
    expected = client.get(
        f"/v1/evaluations/{first}/frames",
        params={"class": "Pedestrian", "metric": "bev", "difficulty": "hard", "set": "loose"},
    ).json()["frames"]
    html = client.get(f"/evaluations/{first}", params=params).text
    assert worst_table(html) == [[f["frame"], str(f["tp"]), str(f["fp"]), str(f["fn"])] for f in expected]
    page = Page(html)
    selected = {a.get("value") for t, a in page.tags if t == "option" and "selected" in a}
    assert {"Pedestrian", "bev", "hard", "loose"} <= selected
    assert all("cls=Pedestrian&metric=bev&difficulty=hard&set=loose" in r["href"] for r in frame_rows(page))


def test_worst_frames_show_why_they_cannot(client, two) -> None:
    first, _ = two
    r = client.get(f"/evaluations/{first}", params={"cls": "Bogus"})
    assert r.status_code == 200 and "Bogus" in Page(r.text).all_text()
    assert '<table class="frames">' not in r.text
    uploaded = upload(client, DEMO_PRED, "result.pkl.gz", gt=None, gt_file=("gt.pkl.gz", demo_paths()[0].read_bytes()))
    assert uploaded.status_code == 201
    r = client.get(f"/evaluations/{uploaded.json()['id']}")
    assert r.status_code == 200
    assert "used a ground truth uploaded with the request" in Page(r.text).all_text()
    assert len(Page(r.text).cells) == 144  # the scores are still there


def test_frame_view_shows_the_labels_of_each_evaluation(client, two) -> None:
    first, second = two
    frame = client.get(f"/v1/evaluations/{first}/frames").json()["frames"][0]["frame"]
    expected = client.get(f"/v1/frames/{frame}", params=[("evaluation", first), ("evaluation", second)]).json()
    r = client.get(f"/frames/{frame}", params=[("e", first), ("e", second)])
    assert r.status_code == 200
    page = Page(r.text)
    assert [a["data-evaluation"] for t, a in page.tags if t == "section"] == [first, second]
    assert page.svgs == 2
    gt_roles = [g["role"] for g in expected["ground_truth"]]
    assert [c[0] for c in page.classes("span", "badge")[: len(gt_roles)]] == gt_roles
    drawn_gt = [g for g in expected["ground_truth"] if min(g["dimensions"]) > 0]  # DontCare has no box
    assert len(drawn_gt) < len(gt_roles)
    for name, model in expected["models"].items():
        eid = model["evaluation"]
        labels = [d["label"] for d in model["detections"]]
        assert page.classes("tr", "det", eid) == [[label] for label in labels]
        assert [c for c in page.classes("span", "badge", eid) if c[0] not in ("tp", "fp", "fn")] == [
            [label] for label in labels if label not in ("tp", "fp")
        ]
        missed = set(model["missed"])
        assert page.classes("g", "box", eid) == [
            ["gt", "missed"] if g["index"] in missed else ["gt"] for g in drawn_gt
        ] + [[label] for label in labels]
        text = page.all_text()
        assert name in text
        assert f"TP {model['counts']['tp']}" in text and f"FP {model['counts']['fp']}" in text
    remove = [a["href"] for t, a in page.tags if t == "a" and "remove" in a.get("class", "")]
    assert remove == [
        f"/frames/{frame}?e={second}&cls=Car&metric=3d&difficulty=moderate&set=strict",
        f"/frames/{frame}?e={first}&cls=Car&metric=3d&difficulty=moderate&set=strict",
    ]


def test_frame_view_offers_the_other_evaluations(client, two) -> None:
    first, second = two
    page = Page(client.get("/frames/000000", params={"e": first}).text)
    offered = [a["value"] for t, a in page.tags if t == "option" and len(a.get("value", "")) == 32]
    assert second in offered and first not in offered
    hidden = [a["value"] for t, a in page.tags if t == "input" and a.get("type") == "hidden"]
    assert hidden == [first]


def test_frame_view_score_threshold(client, two) -> None:
    first, _ = two
    expected = client.get("/v1/frames/000000", params={"evaluation": first, "score_threshold": 0.5}).json()
    page = Page(client.get("/frames/000000", params={"e": first, "score": "0.5"}).text)
    rows = [a["class"].split()[1] for t, a in page.tags if t == "tr" and a.get("class", "").startswith("det ")]
    assert rows == [d["label"] for m in expected["models"].values() for d in m["detections"]]
    assert "below_threshold" in rows


@pytest.mark.parametrize(
    ("query", "status", "needle"),
    [
        ("/frames/999999?e={first}", 404, "no frame 999999"),
        ("/frames/000000?e=nope", 404, "no evaluation with id 'nope'"),
        ("/frames/000000", 422, "name at least one evaluation"),
        ("/frames/000000?e={first}&score=high", 422, "score threshold must be a number"),
        ("/frames/000000?e={first}&cls=Bogus", 422, "Bogus"),
        ("/frames/000000?e={first}&e={uploaded}", 409, "different ground truths"),
    ],
)
def test_frame_view_errors_are_html(client, two, query, status, needle) -> None:
    first, _ = two
    uploaded = upload(
        client, golden_bytes("result.pkl"), gt=None, gt_file=("gt.pkl", golden_bytes("kitti_infos_val.pkl"))
    ).json()["id"]
    page = assert_html_error(client.get(query.format(first=first, uploaded=uploaded)), status, needle)
    assert any(t == "form" for t, _ in page.tags)  # the choices stay on the page


def css_rules() -> dict[str, dict[str, str]]:
    """``selector -> {property: value}`` of app.css (each selector of a list on its own), ``var()`` resolved."""
    text = re.sub(r"/\*.*?\*/", "", (STATIC_DIR / "app.css").read_text(), flags=re.S)
    rules: dict[str, dict[str, str]] = {}
    for selectors, body in re.findall(r"([^{}]+)\{([^}]*)\}", text):
        declarations = {k.strip(): v.strip() for k, v in (d.split(":", 1) for d in body.split(";") if ":" in d)}
        for selector in selectors.split(","):
            rules.setdefault(" ".join(selector.split()), {}).update(declarations)
    root = rules[":root"]

    def resolve(value: str) -> str:
        return re.sub(r"var\((--[\w-]+)\)", lambda m: root[m[1]], value)

    return {s: {k: resolve(v) for k, v in d.items()} for s, d in rules.items()}


# Machado, Oliveira & Fernandes (2009), severity 1: linear RGB as people with each dichromacy see it
_DICHROMACY = {
    "protanopia": ((0.152286, 1.052583, -0.204868), (0.114503, 0.786281, 0.099216), (-0.003882, -0.048116, 1.051998)),
    "deuteranopia": ((0.367322, 0.860646, -0.227968), (0.280085, 0.672501, 0.047413), (-0.01182, 0.04294, 0.968881)),
    "tritanopia": ((1.255528, -0.076749, -0.178779), (-0.078411, 0.930809, 0.147602), (0.004733, 0.691367, 0.3039)),
}


def lab(colour: str, vision: str | None = None) -> tuple[float, float, float]:
    """CIELAB (D65) of a ``#rrggbb`` colour, as seen with normal vision or with a dichromacy."""
    srgb = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
    rgb = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in srgb]
    if vision is not None:
        rgb = [min(max(sum(m * c for m, c in zip(row, rgb)), 0.0), 1.0) for row in _DICHROMACY[vision]]
    xyz = [
        sum(m * c for m, c in zip(row, rgb)) / white
        for row, white in zip(
            ((0.4124, 0.3576, 0.1805), (0.2126, 0.7152, 0.0722), (0.0193, 0.1192, 0.9505)), (0.95047, 1.0, 1.08883)
        )
    ]
    fx, fy, fz = (t ** (1 / 3) if t > 216 / 24389 else (24389 / 27 * t + 16) / 116 for t in xyz)
    return 116 * fy - 16, 500 * (fx - fy), 200 * (fy - fz)


def test_frame_view_tells_missed_from_false_positives_in_any_vision() -> None:
    rules = css_rules()
    stroke = {
        "missed": rules["svg.bev .box.gt.missed polygon"]["stroke"],
        "fp": rules["svg.bev .box.fp > *"]["stroke"],
        "tp": rules["svg.bev .box.tp > *"]["stroke"],
    }
    # the legend's keys and the badges (FN counts, fp labels) use the boxes' colours
    assert rules[".key.missed"]["border-color"] == stroke["missed"] and rules[".key.fp"]["border-color"] == stroke["fp"]
    assert rules[".key.tp"]["border-color"] == stroke["tp"]
    badge = {kind: rules[f".badge.{kind}"]["background"] for kind in ("missed", "fn", "fp", "tp")}
    assert badge["missed"] == badge["fn"] and len({badge["fn"], badge["fp"], badge["tp"]}) == 3
    # missed is also told by its shape: an outline, dashed, no fill (detections are filled)
    assert rules["svg.bev .box.gt polygon"]["fill"] == "none" and "stroke-dasharray" in rules["svg.bev .box.gt polygon"]
    for vision in (None, *_DICHROMACY):
        seen = {kind: lab(colour, vision) for kind, colour in stroke.items()}
        for a, b in (("missed", "fp"), ("tp", "fp"), ("tp", "missed")):
            assert math.dist(seen[a], seen[b]) > 20, (a, b, vision or "normal vision")


def test_frame_view_has_a_legend_of_every_kind_of_box(client, two) -> None:
    first, _ = two
    html = client.get("/frames/000000", params={"e": first}).text
    legend = html.split('<p class="legend-bev">', 1)[1].split("</p>", 1)[0]
    pairs = re.findall(r'<span class="key (\w+)"></span>([^<]*)', legend)
    keys = {kind: " ".join(label.split()) for kind, label in pairs}
    assert list(keys) == ["gt", "missed", "tp", "fp", "ignored", "below_threshold"]
    assert keys["missed"] == "missed ground truth (FN)" and keys["fp"] == "false positive (fp)"
    assert keys["tp"] == "true positive (tp)"


# ------------------------------------------------------------------------------------------ no internet

_URL_IN_CSS = re.compile(r"url\(\s*['\"]?([^'\")\s]+)")
_IMPORT_IN_CSS = re.compile(r"@import\s+['\"]([^'\"]+)")


def _external(url: str) -> bool:
    url = url.strip().lower()
    if url.startswith(("http://127.0.0.1", "https://127.0.0.1")):
        return False
    return url.startswith(("http:", "https:", "//", "ftp:"))


def test_no_page_or_static_file_fetches_from_the_internet(client, two) -> None:
    first, second = two
    pages = [
        "/",
        f"/evaluations/{first}",
        f"/compare?a={first}&b={second}",
        "/evaluations/nope",
        f"/frames/000000?e={first}",
    ]
    static = sorted(p for p in STATIC_DIR.iterdir() if p.is_file())
    assert {p.name for p in static} == {"app.css", "app.js"}
    for path in pages:
        html = client.get(path).text
        page = Page(html)
        assert page.urls, path
        bad = [u for u in page.urls if _external(u)]
        bad += [u for u in _URL_IN_CSS.findall(html) + _IMPORT_IN_CSS.findall(html) if _external(u)]
        assert not bad, (path, bad)
        assert "/static/app.css" in page.urls and "/static/app.js" in page.urls
    for file in static:
        r = client.get(f"/static/{file.name}")
        assert r.status_code == 200 and r.text == file.read_text()
        urls = _URL_IN_CSS.findall(r.text) + _IMPORT_IN_CSS.findall(r.text)
        urls += re.findall(r"""(?:fetch|import)\s*\(\s*['"`]([^'"`]+)""", r.text)
        assert not [u for u in urls if _external(u)], file.name
        assert "http://" not in r.text and "https://" not in r.text, file.name


def test_the_api_docs_are_served_by_the_service_itself(client) -> None:
    r = client.get("/docs")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "http://" not in r.text and "https://" not in r.text and "//cdn" not in r.text
    page = Page(r.text)
    urls = page.urls + re.findall(r"""\burl:\s*['"]([^'"]+)""", r.text)  # and the document Swagger UI loads
    scripts = [a["src"] for t, a in page.tags if t == "script" and "src" in a]
    styles = [a["href"] for t, a in page.tags if t == "link" and a.get("rel") == "stylesheet"]
    assert scripts and styles and "/openapi.json" in urls
    for url in urls:
        assert url.startswith("/") and not url.startswith("//"), url
        asset = client.get(url)
        assert asset.status_code == 200 and asset.content, url
    assert all("javascript" in client.get(src).headers["content-type"] for src in scripts)
    assert all(client.get(href).headers["content-type"].startswith("text/css") for href in styles)
    assert client.get("/redoc").status_code == 404  # ReDoc's bundle fetches its logo from cdn.redoc.ly


def test_pages_are_not_in_the_openapi_document(client) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    assert not {"/", "/ui/evaluations", "/evaluations/{evaluation_id}", "/compare", "/frames/{frame_id}"} & set(paths)


# -------------------------------------------------------------------------------------------------- SVG


def test_plot_maps_recall_and_precision_to_the_corners() -> None:
    plot = Plot(width=200, height=100, left=30, right=10, top=5, bottom=20)
    assert plot.point(0.0, 0.0) == (30.0, 80.0)  # bottom-left of the chart area
    assert plot.point(1.0, 1.0) == (190.0, 5.0)  # top-right
    assert plot.point(0.5, 0.25) == (110.0, 61.25)


def test_pr_chart_puts_the_41_points_at_the_sampled_recalls() -> None:
    plot = Plot(width=140, height=60, left=20, right=0, top=0, bottom=20)  # chart area 120 × 40
    precision = [1.0] * 20 + [0.5] * 10 + [0.0] * 11
    chart = pr_chart({"moderate": {"precision": precision, "recall": [0.75] * 41}}, {"moderate": 61.0}, plot)
    (line,) = chart.lines
    assert line.difficulty == "moderate" and line.count == 41 and line.ap == 61.0
    points = [tuple(map(float, p.split(","))) for p in line.points.split()]
    assert points[0] == (20.0, 0.0) and points[20] == (80.0, 20.0) and points[40] == (140.0, 40.0)
    assert [x for x, _ in points] == pytest.approx([20 + 3 * i for i in range(41)])


def test_bev_corners_follow_the_camera_convention() -> None:
    # rotation 0: the length along +x
    assert bev_corners([1.0, 1.6, 2.0], [4.0, 1.5, 2.0], 0.0) == [(3.0, 3.0), (3.0, 1.0), (-1.0, 1.0), (-1.0, 3.0)]
    # rotation pi/2: cos 0, sin 1 -> (x + b, z - a): the length along -z
    corners = bev_corners([1.0, 1.6, 2.0], [4.0, 1.5, 2.0], math.pi / 2)
    assert [c for xz in corners for c in xz] == pytest.approx([2.0, 0.0, 0.0, 0.0, 0.0, 4.0, 2.0, 4.0])
    # rotation 0.3 (cos 0.955336, sin 0.295520), l 4, w 2 at (0, z 10): front-left a=+2, b=+1
    corners = bev_corners([0.0, 1.6, 10.0], [4.0, 1.5, 2.0], 0.3)
    assert corners[0] == pytest.approx((2 * 0.955336 + 0.295520, 10 - 2 * 0.295520 + 0.955336), abs=1e-5)
    assert corners[2] == pytest.approx((-2 * 0.955336 - 0.295520, 10 + 2 * 0.295520 - 0.955336), abs=1e-5)


def test_bev_view_draws_z_up_and_x_right_at_one_scale() -> None:
    near = {"index": 0, "name": "Car", "location": [0.0, 1.6, 5.0], "dimensions": [2.0, 1.5, 2.0], "rotation_y": 0.0}
    far = {**near, "index": 1, "location": [10.0, 1.6, 30.0]}
    det = {**far, "index": 0, "label": "fp", "score": 0.5}
    dontcare = {
        "index": 2,
        "name": "DontCare",
        "location": [-1000.0, -1000.0, -1000.0],
        "dimensions": [-1.0, -1.0, -1.0],
        "rotation_y": -10.0,
    }
    view = bev_view([near, far, dontcare], [det], width=300, height=300)
    assert [b.kind for b in view.boxes] == ["gt", "gt", "fp"]  # no box for DontCare, nor room made for it
    assert view.step == 5.0

    def box(i: int) -> list[tuple[float, float]]:
        return [tuple(map(float, p.split(","))) for p in view.boxes[i].points.split()]

    (nx, ny), (fx, fy) = (tuple(sum(c) / 4 for c in zip(*box(i))) for i in (0, 1))
    assert fy < ny and fx > nx  # farther (larger z) is higher on screen, larger x is to the right
    xs, ys = zip(*box(0))
    assert max(xs) - min(xs) == pytest.approx(max(ys) - min(ys))  # a square box stays square
    assert box(1) == box(2)  # the detection sits on the box it duplicates
    assert all(0 <= v <= 300 for i in range(3) for p in box(i) for v in p)
    cx, cy = view.origin
    assert cy > ny and 0 <= cx <= 300  # the camera is below (behind) everything
    (hx0, hy0), (hx1, hy1) = view.boxes[0].heading
    assert hx1 > hx0 and hy1 == pytest.approx(hy0)  # rotation 0 faces +x, to the right
