"""The evaluation page's error decomposition: a bar chart per class (inline SVG) and the true-positive errors."""

from __future__ import annotations

import itertools
import math
import re
from typing import Any

import pytest
from server_helpers import upload
from test_web_pages import _DICHROMACY, Page, _external, css_rules, evaluation_id, lab, submit

from kitti_eval.analysis.decomposition import AOS_TYPES, ERROR_TYPES, TP_ERRORS
from kitti_eval.demo import demo_paths
from kitti_eval_server.web.svg import bar_chart

DEMO_PRED = demo_paths()[1].read_bytes()
METRICS = ("bbox", "bev", "3d", "aos")


@pytest.fixture(scope="module")
def with_errors(client) -> str:
    """The demo uploaded through the page's form with "error decomposition" ticked."""
    return evaluation_id(submit(client, model="pointpillars", errors="true"))


def section(html: str) -> str:
    """The page from the "Why AP is lost" heading to the next heading."""
    return html.split('<h2 id="errors">', 1)[1].split("<h2", 1)[0]


def bars(html: str) -> dict[str, dict[str, Any]]:
    """``"<class>/<metric>/<type>" -> {"value", "text", "rect"}`` of the error charts' bars."""
    out: dict[str, dict[str, Any]] = {}
    bar = r'<g class="bar [\w ]+" data-error="([^"]+)" data-value="([^"]*)">(.*?)</g>'
    for key, value, body in re.findall(bar, html, re.S):
        rect = re.search(r'<rect x="([^"]+)" y="[^"]+" width="([^"]+)"', body)
        text = re.findall(r'<text class="value"[^>]*>([^<]*)</text>', body)
        assert key not in out, key
        out[key] = {"value": value, "text": text[0], "rect": None if rect is None else tuple(map(float, rect.groups()))}
    return out


def tp_cells(html: str) -> dict[str, dict[str, str]]:
    """``"<class>/<difficulty>/<error>" -> {"value", "text"}`` of the true-positive error tables."""
    return {
        key: {"value": value, "text": text.strip()}
        for key, value, text in re.findall(r'<td class="num" data-tp="([^"]+)" data-value="([^"]*)">([^<]*)</td>', html)
    }


# ----------------------------------------------------------------------------------------------- upload


def test_the_upload_form_has_an_error_decomposition_checkbox(client) -> None:
    html = client.get("/").text
    page = Page(html)
    assert ("input", {"type": "checkbox", "name": "errors", "value": "true"}) in page.tags
    form = html.split('<form class="upload"', 1)[1].split("</form>", 1)[0]
    assert re.search(r'<label[^>]*>\s*<input type="checkbox" name="errors" value="true">\s*error decomposition', form)


def test_the_checkbox_asks_for_the_errors(client, with_errors) -> None:
    doc = client.get(f"/v1/evaluations/{with_errors}").json()
    api = upload(client, DEMO_PRED, "result.pkl.gz", fields={"errors": "true"}).json()
    for key in ("errors", "errors_r11", "tp_errors"):
        assert doc[key] == api[key], key
    plain = evaluation_id(submit(client))
    assert "errors" not in client.get(f"/v1/evaluations/{plain}").json()


def test_a_refused_upload_keeps_the_box_ticked(client) -> None:
    r = submit(client, gt="nope", errors="true")
    assert r.status_code == 404
    assert ("input", {"type": "checkbox", "name": "errors", "value": "true", "checked": ""}) in Page(r.text).tags


# ----------------------------------------------------------------------------------------------- the page


def test_the_chart_shows_the_jsons_values_strict_r40_moderate(client, with_errors) -> None:
    doc = client.get(f"/v1/evaluations/{with_errors}").json()
    html = section(client.get(f"/evaluations/{with_errors}").text)
    assert len(re.findall(r'<svg class="errors"', html)) == len(doc["classes"]) == 3
    found = bars(html)
    expected = {
        f"{cls}/{metric}/{kind}": doc["errors"][cls][metric]["moderate"][kind]
        for cls in doc["classes"]
        for metric in METRICS
        for kind in (AOS_TYPES if metric == "aos" else ERROR_TYPES)
    }
    assert list(found) == list(expected)  # class by class, metric by metric, the types in their order
    for key, value in expected.items():
        assert found[key]["value"] == repr(value), key
        assert found[key]["text"] == f"{value:.2f}", key
    # one scale for every bar of the page: the width is the value times the same factor
    factors = {round(b["rect"][1] / v, 6) for k, b in found.items() if (v := expected[k]) > 0}
    assert len(factors) == 1
    zero = {b["rect"][0] for b in found.values()}
    assert len(zero) == 1  # every bar starts at 0
    assert "strict" in html and "R40" in html and "moderate" in html


def test_the_chart_labels_each_bar_and_group(client, with_errors) -> None:
    html = section(client.get(f"/evaluations/{with_errors}").text)
    svg = html.split('<svg class="errors"', 1)[1].split("</svg>", 1)[0]
    labels = re.findall(r'<text class="label"[^>]*>([^<]*)</text>', svg)
    assert labels == [k for m in METRICS for k in (AOS_TYPES if m == "aos" else ERROR_TYPES)]
    assert re.findall(r'<text class="group"[^>]*>([^<]*)</text>', svg) == list(METRICS)
    assert "AP points" in svg


def test_the_true_positive_errors_are_a_table_per_class(client, with_errors) -> None:
    doc = client.get(f"/v1/evaluations/{with_errors}").json()
    cells = tp_cells(section(client.get(f"/evaluations/{with_errors}").text))
    expected = {
        f"{cls}/{d}/{name}": doc["tp_errors"][cls][d][name]
        for cls in doc["classes"]
        for d in ("easy", "moderate", "hard")
        for name in TP_ERRORS
    }
    assert list(cells) == list(expected)
    for key, value in expected.items():
        assert cells[key] == {"value": repr(value), "text": f"{value:.3f}"}, key


def test_the_difficulty_and_recall_can_be_chosen(client, with_errors) -> None:
    doc = client.get(f"/v1/evaluations/{with_errors}").json()
    page = client.get(f"/evaluations/{with_errors}", params={"err_difficulty": "hard", "err_recall": "R11"}).text
    found = bars(section(page))
    for key, bar in found.items():
        cls, metric, kind = key.split("/")
        assert bar["value"] == repr(doc["errors_r11"][cls][metric]["hard"][kind]), key
    selected = {a.get("value") for t, a in Page(page).tags if t == "option" and "selected" in a}
    assert {"hard", "R11"} <= selected
    # the worst frames' choice and the errors' choice travel with each other's form
    forms = re.findall(r"<form class=\"inline\" method=\"get\".*?</form>", page, re.S)
    assert any('type="hidden" name="err_difficulty" value="hard"' in f for f in forms)
    assert any('type="hidden" name="difficulty" value="moderate"' in f for f in forms)


def test_a_bad_choice_says_so(client, with_errors) -> None:
    r = client.get(f"/evaluations/{with_errors}", params={"err_recall": "R12"})
    assert r.status_code == 200
    html = section(r.text)
    assert "R12" in Page(html).all_text() and '<svg class="errors"' not in html


def test_without_errors_the_page_says_how_to_get_them(client) -> None:
    plain = evaluation_id(submit(client))
    html = client.get(f"/evaluations/{plain}").text
    assert '<svg class="errors"' not in html
    assert "errors=true" in Page(section(html)).all_text()


def test_the_chart_fetches_nothing(client, with_errors) -> None:
    html = client.get(f"/evaluations/{with_errors}").text
    part = section(html)
    assert not [u for u in Page(html).urls if _external(u)]
    assert "http" not in part and "url(" not in part


def test_error_colours_are_told_apart_in_any_vision() -> None:
    rules = css_rules()
    fill = {kind: rules[f"svg.errors .bar.{kind} rect"]["fill"] for kind in AOS_TYPES}
    assert fill["missed"] == rules["svg.bev .box.gt.missed polygon"]["stroke"]  # as missed boxes in the frame view
    assert fill["background"] == rules["svg.bev .box.fp > *"]["stroke"]  # a false positive of nothing
    for vision in (None, *_DICHROMACY):
        for a, b in itertools.combinations(fill, 2):
            assert math.dist(lab(fill[a], vision), lab(fill[b], vision)) > 15, (a, b, vision or "normal vision")


# -------------------------------------------------------------------------------------------------- SVG


def test_bar_chart_puts_zero_and_the_largest_value_on_the_axis() -> None:
    chart = bar_chart({"3d": {"localization": 10.0, "missed": 2.5, "both": None}}, hi=10.0, width=300)
    (group,) = chart.groups
    loc, missed, both = group.bars
    assert chart.x0 == chart.left and chart.ticks[-1][1] == pytest.approx(chart.right)
    assert loc.x == chart.x0 and loc.width == pytest.approx(chart.right - chart.left)
    assert missed.width == pytest.approx(loc.width / 4)
    assert both.value is None and both.width == 0.0 and both.text == "-"
    assert [b.text for b in group.bars] == ["10.00", "2.50", "-"]
    assert loc.y < missed.y < both.y and group.y < loc.y


def test_bar_chart_draws_a_negative_value_left_of_zero() -> None:
    chart = bar_chart({"bev": {"duplicate": -1.0, "missed": 4.0}}, lo=-1.0, hi=4.0)
    dup, missed = chart.groups[0].bars
    assert chart.left < chart.x0 < chart.right
    assert dup.x + dup.width == pytest.approx(chart.x0) and missed.x == chart.x0
    assert dup.text == "-1.00" and missed.width == pytest.approx(4 * dup.width)


def test_bar_chart_never_prints_minus_zero() -> None:
    chart = bar_chart({"3d": {"missed": -1e-12}})
    assert chart.groups[0].bars[0].text == "0.00"
