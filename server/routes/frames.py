"""Frames of stored evaluations: TP/FP/FN per frame (worst first), and one frame's boxes labelled by the
matching for several evaluations side by side."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query

from kitti_eval.analysis.frame_question import ASKED, FrameQuestion

from ..access.deps import ReaderCaller
from ..params import MAX_SCORE, ServiceDep
from ..schemas import ErrorResponse

router = APIRouter(
    tags=["frames"],
    responses={
        404: {"model": ErrorResponse, "description": "unknown evaluation or frame"},
        409: {
            "model": ErrorResponse,
            "description": "the evaluation's inputs were not kept (ground truth uploaded with "
            "the request, or predictions not kept), or the evaluations used "
            "different ground truths",
        },
        422: {"model": ErrorResponse, "description": "unknown class, metric, difficulty or set"},
    },
)

ClassQ = Annotated[str, Query(alias="class", description="the class, e.g. Car")]
MetricQ = Annotated[Literal["bbox", "bev", "3d", "aos"], Query(description="overlap metric (aos: the 2D matching)")]
DifficultyQ = Annotated[Literal["easy", "moderate", "hard"], Query()]
SetQ = Annotated[Literal["strict", "loose"], Query(alias="set", description="IoU threshold set")]
#: most frames a listing asks for (KITTI val has 3769)
MAX_WORST = 1_000_000


def frame_counts_question(
    cls: ClassQ = ASKED.cls,
    metric: MetricQ = ASKED.metric,  # type: ignore[assignment]
    difficulty: DifficultyQ = ASKED.difficulty,  # type: ignore[assignment]
    oset: SetQ = ASKED.oset,  # type: ignore[assignment]
    worst: Annotated[
        int | None, Query(ge=1, le=MAX_WORST, description="only the N frames with most errors (FP + FN), 1..10^6")
    ] = 20,
    score_threshold: Annotated[
        float,
        Query(ge=-MAX_SCORE, le=MAX_SCORE, allow_inf_nan=False, description="count detections scoring at least this"),
    ] = ASKED.score_threshold,
) -> dict[str, Any]:
    """The query of a TP/FP/FN-per-frame listing (an evaluation's, a submission's), as keyword arguments: the
    question (:class:`~kitti_eval.analysis.diagnostics.FrameQuestion`) and how many frames."""
    return {"question": FrameQuestion(cls, metric, difficulty, oset, score_threshold), "worst": worst}


#: a frame listing's query, for the routes that answer one
FrameCountsQ = Annotated[dict[str, Any], Depends(frame_counts_question)]


@router.get("/v1/evaluations/{evaluation_id}/frames", summary="TP, FP and FN per frame, worst first")
async def evaluation_frames(
    service: ServiceDep,
    caller: ReaderCaller,
    evaluation_id: str,
    question: FrameCountsQ,
) -> dict[str, Any]:
    """The counts come from the same matching as the AP (as `kitti-eval frames`): frames ranked by FP + FN,
    ties by more misses. Needs an evaluation against a registered ground truth whose predictions were kept."""
    return await service.run(lambda: service.evaluation_frames.frames(evaluation_id, caller=caller, **question))


@router.get("/v1/frames/{frame_id}", summary="One frame's boxes, labelled, for several evaluations")
async def inspect_frame(
    service: ServiceDep,
    caller: ReaderCaller,
    frame_id: str,
    evaluation: Annotated[list[str], Query(description="evaluation id; repeat for several (same ground truth)")],
    cls: ClassQ = "Car",
    metric: MetricQ = "3d",
    difficulty: DifficultyQ = "moderate",
    oset: SetQ = "strict",
    score_threshold: Annotated[
        float | None,
        Query(
            ge=-MAX_SCORE,
            le=MAX_SCORE,
            allow_inf_nan=False,
            description="detections scoring below this take no part",
        ),
    ] = None,
) -> dict[str, Any]:
    """As `kitti-eval inspect --format json`: the ground truth with its role for the class, and per
    evaluation every detection labelled (tp with its ground truth and IoU, fp and why, ignored, dontcare,
    below_threshold, other_class), the ground truth's labels, the missed boxes and the counts."""
    return await service.run(
        lambda: service.evaluation_frames.inspect(
            evaluation,
            frame_id,
            cls=cls,
            metric=metric,
            difficulty=difficulty,
            oset=oset,
            score_threshold=score_threshold,
            caller=caller,
        )
    )
