"""``/v1/ground-truths``: named ground-truth sets. Registering and deleting need the admin token."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Response, UploadFile
from fastapi.responses import JSONResponse

from ..access.deps import AdminCaller, ReaderCaller
from ..ground_truths.cache import NAME_PATTERN
from ..params import ServiceDep
from ..schemas import ErrorResponse, GroundTruthList, GroundTruthOut, ground_truth_out
from ..service import FileIn

router = APIRouter(
    prefix="/v1/ground-truths",
    tags=["ground truths"],
    responses={404: {"model": ErrorResponse, "description": "no ground truth of that name"}},
)

_admin_errors: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "no admin token given"},
    403: {"model": ErrorResponse, "description": "wrong admin token"},
}


@router.post(
    "",
    status_code=201,
    response_model=GroundTruthOut,
    summary="Register a named ground truth (admin)",
    responses={
        **_admin_errors,
        409: {"model": ErrorResponse, "description": "the name is taken"},
        422: {"model": ErrorResponse, "description": "invalid or unsafe file"},
    },
)
async def register_ground_truth(
    service: ServiceDep,
    admin: AdminCaller,
    name: Annotated[str, Form(pattern=NAME_PATTERN, description="e.g. kitti-val")],
    file: Annotated[UploadFile, File(description="an OpenPCDet infos .pkl[.gz], or a zip/tar of a label_2 folder")],
    project: Annotated[
        str | None, Form(description="only this project's members see and use it (default: everyone)")
    ] = None,
    sealed: Annotated[
        bool,
        Form(description="a test set: only aggregate results ever leave the service, no per-frame view"),
    ] = False,
) -> JSONResponse:
    """Validate the file by loading it, keep it, and make it available as `gt=<name>`."""
    record = await service.run(
        lambda: service.gt_catalog.add(
            name, FileIn(file.file, file.filename), caller=admin, project=project or None, sealed=sealed
        )
    )
    return JSONResponse(
        ground_truth_out(record), status_code=201, headers={"Location": f"/v1/ground-truths/{record.name}"}
    )


@router.get("", response_model=GroundTruthList, summary="Registered ground truths")
def list_ground_truths(service: ServiceDep, caller: ReaderCaller) -> dict[str, Any]:
    return {"items": [ground_truth_out(r) for r in service.gt_catalog.listed(caller)]}


@router.get("/{name}", response_model=GroundTruthOut, summary="One registered ground truth")
def get_ground_truth(service: ServiceDep, caller: ReaderCaller, name: str) -> dict[str, Any]:
    return ground_truth_out(service.gt_catalog.get(name, caller))


@router.delete(
    "/{name}",
    status_code=204,
    responses=_admin_errors,
    summary="Delete a registered ground truth (admin); evaluations made with it stay",
)
def delete_ground_truth(service: ServiceDep, admin: AdminCaller, name: str) -> Response:
    service.gt_catalog.remove(name, caller=admin)
    return Response(status_code=204)
