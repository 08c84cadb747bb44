"""/v1/models: upload, list, read and delete models."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse

from phd_core.renderers import FAMILIES, family_titles

from ..budget import largest_model_file
from ..deps import ERRORS, Caller, Service
from ..errors import not_found
from ..folders import remove_folder
from ..requests import stored_up
from ..schemas import Calibration, ModelInfo, ModelList, PosesRequest, TrainingCameras
from ..store import ModelRecord
from ..upload import receive_upload, sniff_kind
from ..work import export_poses

router = APIRouter(prefix="/v1", responses=ERRORS, tags=["models"])
UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "properties": {
        "file": {"type": "string", "format": "binary", "description": "The model: " + family_titles("or")},
        "files": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": "Instead of "
                  "file: a folder, one part per file named by its path inside it (a PLY with the sidecar phd train "
                  "wrote beside it, or a reference-trainer, splatfacto or gsplat output folder)"},
        "archive": {"type": "string", "format": "binary", "description": "Instead of file: such a folder as a zip"},
        "cameras": {"type": "string", "description": "Training cameras as JSON (transforms.json or a list of frames)"},
        "name": {"type": "string", "description": "Display name (default: the file name)"},
        "background": {"type": "string", "description": "Splat models: the colour trained over, [r, g, b] in [0, 1] "
                       "or white/black/grey. Default: what the file or its cameras say, else white (docs/service.md)"},
        "camera_format": {"type": "string", "description": "The pose convention of the cameras' source (colmap, "
                          "3dgs-output, nerfstudio, blender); default: 3dgs-output for a cameras.json, "
                          "else nerfstudio"},
    }}}}}}


def model_info(record: ModelRecord) -> ModelInfo:
    facts = record.describe
    bounds = facts.get("bounds")
    family = FAMILIES.get(record.kind)
    network = {k: facts[k] for k in (family.network if family else ()) if k in facts} or None
    return ModelInfo(
        id=record.id, name=record.name, kind=record.kind, num_units=record.num_units,
        sh_degree=facts.get("sh_degree") if isinstance(facts.get("sh_degree"), int) else None,
        network=network,
        bounds=bounds if isinstance(bounds, dict) and all(isinstance(v, list) for v in bounds.values()) else None,
        size_bytes=record.size_bytes, sha256=record.sha256, created_at=record.created_at,
        has_training_cameras=bool(record.training_frames),
        num_training_cameras=len(record.training_frames or []),
        has_calibration=record.calibration is not None,
        calibration=None if record.calibration is None else Calibration(**record.calibration),
        camera_format=facts.get("camera_format"),
        details=facts)


@router.post("/models", status_code=201, response_model=ModelInfo, openapi_extra=UPLOAD_BODY,
             description=f"Upload a model ({family_titles('or')}) with optional training cameras.")
async def upload_model(request: Request, svc: Service, who: Caller) -> JSONResponse:
    temp = svc.store.new_temp_path()
    folder = temp.with_suffix(".folder")   # a folder's files (service.folders)
    try:
        upload = await receive_upload(request, temp, svc.settings.max_camera_json_bytes,
                                      largest_model_file(svc.settings.memory_budget_bytes), folder,
                                      keep_free=svc.settings.keep_free_bytes)
        if upload.folder is not None:
            record = await asyncio.to_thread(svc.ingest_folder, upload, who)
        else:
            record = await asyncio.to_thread(svc.ingest, upload, sniff_kind(upload.head), who)
    finally:
        temp.unlink(missing_ok=True)  # gone already after a successful move into the store
        await asyncio.to_thread(remove_folder, folder)
    info = model_info(record)
    info.note = upload.note                 # an upload identical to a stored model: 200 and that model
    return JSONResponse(info.model_dump(mode="json"), status_code=201 if upload.note is None else 200,
                        headers={"Location": f"/v1/models/{record.id}"})


@router.get("/models", response_model=ModelList)
async def list_models(svc: Service, who: Caller) -> ModelList:
    records = await asyncio.to_thread(svc.store.list)
    return ModelList(models=[model_info(r) for r in records if who.may_see(r.owner)])


@router.get("/models/{model_id}", response_model=ModelInfo)
async def get_model(model_id: str, svc: Service, who: Caller) -> ModelInfo:
    return model_info(svc.model(model_id, who))


@router.get("/models/{model_id}/cameras", response_model=TrainingCameras)
async def get_training_cameras(model_id: str, svc: Service, who: Caller) -> TrainingCameras:
    """The stored training cameras as frames and the capture's up (the page plots them, places
    candidates around them and stands its 3D view on that up)."""
    record = svc.model(model_id, who)                    # 404 for another key's model
    up, rule = await asyncio.to_thread(stored_up, record)
    return TrainingCameras(frames=record.training_frames or [], up=up, up_rule=rule)


@router.post("/models/{model_id}/poses", response_class=Response, responses={200: {
    "description": "The poses as the convention's file: JSON (transforms.json, cameras.json) or a zip (COLMAP)",
    "content": {"application/json": {}, "application/zip": {}}}})
async def download_poses(model_id: str, body: PosesRequest, svc: Service, who: Caller) -> Response:
    """Ranked poses as the files a capture tool reads, in the model's own pose convention (or the one
    asked for), written exactly as `phd rank --export` writes them."""
    record = svc.model(model_id, who)
    poses = await asyncio.to_thread(export_poses, record, body, svc.settings)
    return Response(poses.content, media_type=poses.media_type,
                    headers={"Content-Disposition": f'attachment; filename="{poses.filename}"'})


@router.delete("/models/{model_id}", status_code=204)
async def delete_model(model_id: str, svc: Service, who: Caller) -> Response:
    svc.model(model_id, who)                # 404 for another key's model
    if not await asyncio.to_thread(svc.store.delete, model_id):
        raise not_found("model", model_id)
    svc.ledger.forget(model_id)
    return Response(status_code=204)
