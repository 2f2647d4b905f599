"""Downloads of stored objects with HTTP ``Range`` (one range: ``bytes=a-b``, ``bytes=a-``, ``bytes=-n``).

The local backend's files go out as Starlette's ``FileResponse`` (which does ranges itself); an object of another
backend (S3) is streamed from a ranged ``GET`` in blocks, so that the API holds one block of a download in memory,
not the file: 206 with ``Content-Range`` for a range, 416 with ``Content-Range: bytes */size`` for one past the
end, 200 with ``Accept-Ranges: bytes`` otherwise.
"""

from __future__ import annotations

import re

from fastapi.concurrency import run_in_threadpool
from starlette.responses import FileResponse, RedirectResponse, Response, StreamingResponse

from service.errors import NotFound
from service.storage import Storage
from service.storage.objects import ObjectInfo, RangeNotSatisfiable

_RANGE = re.compile(r"^\s*bytes\s*=\s*(\d*)\s*-\s*(\d*)\s*$")


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """``[start, end)`` of a single ``Range`` header against ``size`` bytes; None for none (or one not understood,
    which is served whole, as RFC 9110 allows). Raises :class:`RangeNotSatisfiable` for one past the end."""
    match = _RANGE.match(header or "")
    if match is None or match.group(1) == match.group(2) == "":
        return None
    first, last = match.group(1), match.group(2)
    if first == "":  # the last n bytes
        n = int(last)
        if n == 0:
            raise RangeNotSatisfiable("range", size, size)
        return max(0, size - n), size
    start = int(first)
    end = size if last == "" else min(int(last) + 1, size)
    if start >= size or end <= start:
        raise RangeNotSatisfiable("range", start, size)
    return start, end


async def signed_redirect(storage: Storage, key: str, expires_s: int) -> Response | None:
    """A 307 to a link of the object store that downloads ``key`` for ``expires_s`` (Range works there too), or None
    where there is none a client could follow: the local backend (the API is the store), or S3 reachable only from
    the service's network (no ``PANOGS_S3_PUBLIC_ENDPOINT_URL``)."""
    url = await run_in_threadpool(storage.download_link, key, expires_s)
    if url is None:
        return None
    return RedirectResponse(url, status_code=307, headers={"Cache-Control": "no-store"})


async def object_response(
    storage: Storage, key: str, range_header: str | None, *, media_type: str, filename: str, headers: dict[str, str]
) -> Response:
    """The object ``key`` as a download (whole or the requested range)."""
    disposition = {"Content-Disposition": f'attachment; filename="{filename}"'}
    path = storage.served_file(key)
    if path is not None:
        return FileResponse(path, media_type=media_type, filename=filename, headers=headers)
    info: ObjectInfo | None = await run_in_threadpool(storage.objects.stat, key)
    if info is None:
        raise NotFound("artifact", filename)
    base = {**headers, **disposition, "Accept-Ranges": "bytes"}
    try:
        span = parse_range(range_header, info.size)
    except RangeNotSatisfiable:
        return Response(status_code=416, headers={**base, "Content-Range": f"bytes */{info.size}"})
    start, end = span if span is not None else (0, info.size)
    blocks = await run_in_threadpool(storage.objects.read_range, key, start, end)
    length = {"Content-Length": str(end - start)}
    if span is None:
        return StreamingResponse(blocks, media_type=media_type, headers={**base, **length})
    content_range = {"Content-Range": f"bytes {start}-{end - 1}/{info.size}"}
    return StreamingResponse(
        blocks, status_code=206, media_type=media_type, headers={**base, **length, **content_range}
    )
