"""A browser opening a page the service does not have is shown a page saying so (404), not the API's JSON; a
program asking the API for a path it does not have still reads the JSON error."""

from __future__ import annotations

from server_helpers import app_client

HTML = {"Accept": "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"}


def test_an_unknown_page_is_a_page_and_an_unknown_api_path_json(tmp_path) -> None:
    with app_client(tmp_path / "data") as c:
        page = c.get("/evaluations", headers=HTML)
        assert page.status_code == 404 and page.headers["content-type"].startswith("text/html")
        assert "<!doctype html>" in page.text.lower() and "Not Found" in page.text
        api = c.get("/v1/nowhere", headers=HTML)
        assert api.status_code == 404 and api.json()["error"]["code"] == "not_found"
        program = c.get("/evaluations")  # no HTML asked for: the one error shape
        assert program.status_code == 404 and program.json()["error"]["code"] == "not_found"
