"""``GET /metrics``: the service's metrics in Prometheus' text format (:mod:`kitti_eval_server.observability`)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import APIRouter, Request, Response, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ..errors import Forbidden, NotFound, Unauthorized
from ..observability import CONTENT_TYPE, Metrics

router = APIRouter(tags=["health"])

_bearer = HTTPBearer(auto_error=False, description="KITTI_EVAL_METRICS_TOKEN, when the operator set one")


@router.get(
    "/metrics",
    summary="Metrics in Prometheus' text format",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE: {}}}},
)
def metrics(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)]
) -> Response:
    found: Metrics | None = request.app.state.metrics
    if found is None:
        raise NotFound("metrics are off (KITTI_EVAL_METRICS=off)")
    token = request.app.state.service.settings.metrics_token
    if token is not None:
        if credentials is None:
            raise Unauthorized("the metrics need their token: send 'Authorization: Bearer <KITTI_EVAL_METRICS_TOKEN>'")
        if not hmac.compare_digest(credentials.credentials.encode(), token.get_secret_value().encode()):
            raise Forbidden("the metrics token is not valid")
    return Response(found.render(), media_type=CONTENT_TYPE)
