"""``GET /metrics``: the service's metrics in Prometheus' text format (:mod:`kitti_eval_server.observability`)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from ..access.deps import ScraperCaller
from ..errors import NotFound
from ..observability import CONTENT_TYPE, Metrics

router = APIRouter(tags=["health"])


@router.get(
    "/metrics",
    summary="Metrics in Prometheus' text format",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE: {}}}},
)
def metrics(request: Request, caller: ScraperCaller) -> Response:
    """KITTI_EVAL_METRICS_TOKEN when the operator set one (a scraper's own token), else as any reader."""
    found: Metrics | None = request.app.state.metrics
    if found is None:
        raise NotFound("metrics are off (KITTI_EVAL_METRICS=off)")
    return Response(found.render(), media_type=CONTENT_TYPE)
