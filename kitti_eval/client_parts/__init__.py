"""The parts :class:`kitti_eval.client.Client` is composed of, one module an area: the client's own files
(:mod:`.files`: written readable by their owner only), the idempotency keys of submissions not yet shown scored
(:mod:`.pending`), a benchmark's teams (:mod:`.teams`) and one's entries on a board (:mod:`.entries`).

The HTTP calls of an area are functions of a :class:`Sender` (the client's sending, with its token and
retries); :class:`~kitti_eval.client.Client` has a method for each, which is what the commands call."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import httpx

__all__ = ["Sender"]


class Sender(Protocol):
    """What an area's calls need of the client: its address, and one request sent with its token and retries."""

    service: str

    def _request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        data: Mapping[str, Any] | None = None,
        json_body: Any = None,
        files: Any = None,
        headers: Mapping[str, str] | None = None,
        ok: Sequence[int] = (200, 201, 202),
    ) -> httpx.Response: ...

    def _get(self, path: str, **params: Any) -> Any: ...
