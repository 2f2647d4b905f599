"""``/v1/jobs/{id}/artifacts``: a job's downloadable files, listed and downloaded (with HTTP Range).

They are there once the job's results are (before its appearance fit ends); ``gaussians.ply`` is listed and served
once the fit is done, and answers 409 ``fit_not_ready`` with the fit's progress until then.
"""

from __future__ import annotations

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, Response

from panogs_core.io.run_folder import DOWNLOADABLE, GAUSSIANS_PLY
from service.api.deps import JobDep, SettingsDep, StorageDep
from service.db.models import Job
from service.errors import Conflict, NotFound
from service.job_results import check_fitted
from service.schemas import ArtifactPublic, ArtifactsPublic, error_responses
from service.storage.download import object_response, signed_redirect

router = APIRouter(prefix="/jobs/{job_id}", tags=["results"])
_ERRORS = error_responses(404, 409)


def _finished(job: Job) -> Job:
    if job.results_at is None:
        raise Conflict(f"job {job.id} is {job.state.value}; results exist once its labelling is done")
    return job


@router.get("/artifacts", response_model=ArtifactsPublic, responses=_ERRORS)
def list_artifacts(job: JobDep) -> ArtifactsPublic:
    """The job's downloadable files."""
    data = [
        ArtifactPublic(
            name=a.name,
            size_bytes=a.size_bytes,
            sha256=a.sha256,
            media_type=DOWNLOADABLE[a.name].media_type,
            url=f"/v1/jobs/{job.id}/artifacts/{a.name}",
        )
        for a in _finished(job).artifacts
        if a.name in DOWNLOADABLE  # a row the declaration no longer serves is neither listed nor served
    ]
    return ArtifactsPublic(data=data, count=len(data))


@router.get(
    "/artifacts/{name}",
    response_class=FileResponse,
    responses={
        **_ERRORS,
        200: {"content": {"application/octet-stream": {}}},
        206: {"description": "a byte range"},
        307: {"description": "with redirect=true on S3 reachable by clients: a signed link to the object"},
    },
)
async def download_artifact(
    job: JobDep,
    name: str,
    storage: StorageDep,
    settings: SettingsDep,
    request: Request,
    redirect: bool = Query(False, description="answer 307 to a signed link of the object store, where it has one"),
) -> Response:
    """Download one file of ``panogs_core.io.run_folder.DOWNLOADABLE`` (``panoptic.ply``, ``gaussians.ply`` ...).

    Supports ``Range: bytes=start-end`` (206) to resume an interrupted download. With ``redirect=true`` and object
    storage that the client can reach, the answer is a 307 to a signed link (the bytes then come from the store,
    not through the API); otherwise the file is served here as without it.
    """
    if name == GAUSSIANS_PLY.name:
        check_fitted(job)  # 409 fit_not_ready with the fit's progress until the fitted scene is there
    artifact = next((a for a in _finished(job).artifacts if a.name == name), None)
    if artifact is None or name not in DOWNLOADABLE:
        raise NotFound("artifact", name)
    if redirect:
        moved = await signed_redirect(storage, artifact.path, settings.signed_link_ttl_s)
        if moved is not None:
            return moved
    return await object_response(
        storage,
        artifact.path,
        request.headers.get("range"),
        media_type=DOWNLOADABLE[name].media_type,
        filename=artifact.name,
        headers={"ETag": f'"{artifact.sha256}"', "Cache-Control": "private, max-age=3600"},
    )
