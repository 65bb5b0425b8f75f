"""The benchmark page ``/benchmarks/{name}``: the description and the leaderboard, rendered on the server (no
script needed). Readable without a token when the benchmark is public."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from markupsafe import Markup

from ..benchmarks import Benchmarks, render_markdown
from ..deps import AnyoneCaller
from ..errors import ApiError, clip
from .routes import _render

__all__ = ["router"]

router = APIRouter(include_in_schema=False)


@router.get("/benchmarks/{name}")
def benchmark_page(
    request: Request,
    caller: AnyoneCaller,
    name: str,
    sort: Annotated[str | None, Query(max_length=200)] = None,
    order: Annotated[Literal["asc", "desc"] | None, Query()] = None,
) -> Response:
    benchmarks: Benchmarks = request.app.state.benchmarks
    try:
        bench = benchmarks.get(name, caller)
        board = benchmarks.leaderboard(name, caller, sort=sort, order=order)
    except ApiError as e:
        return _render(request, "error.html", e.status_code, status=e.status_code, message=clip(e.message))
    return _render(
        request,
        "benchmark.html",
        bench=bench.describe(),
        description=Markup(render_markdown(bench.description)),  # noqa: S704 - every character escaped first
        board=board,
    )
