"""Queries and guarded state transitions, shared by the API, the reaper and the worker; one module per resource.

- :mod:`.keys`: a tenant's rows (every read the API makes is scoped to its tenant: another tenant's rows are simply
  not found) and what the tenant uses against its quotas.
- :mod:`.uploads`, :mod:`.scenes`, :mod:`.jobs`, :mod:`.tiles`: each resource's queries.

Every write a worker makes to a running job or tile is guarded by its ``lease`` (the claiming task's id), so a
worker that lost its row (presumed dead and replaced) can no longer change it; those queries are written once for
both kinds of row in :mod:`service.db.leases` (which the reaper and the outbox call directly). The names below
are the package's whole surface: callers write ``crud.<name>``.
"""

from service.db.crud.jobs import (
    cancel_requested,
    cancel_unclaimed,
    claim_job,
    fail_lost,
    fail_unclaimed,
    find_idempotent_job,
    finish_job,
    read_job_row,
    record_results,
    release_job,
    request_cancel,
    undispatched_jobs,
    update_running,
)
from service.db.crud.keys import (
    get_owned,
    job_slots,
    list_owned,
    live_job_slots,
    live_jobs,
    lock_tenant,
    reserved_upload_bytes,
    stored_bytes,
)
from service.db.crud.scenes import get_scene
from service.db.crud.tiles import (
    claim_tile,
    end_tiled_job,
    fan_out,
    finish_merge,
    finish_tile,
    job_queue,
    release_tile,
    tile_rows,
    undispatched_tiles,
    update_tile_running,
)
from service.db.crud.uploads import advance_upload, delete_upload, set_upload_state, stale_uploads
from service.db.leases import stale_cutoff

__all__ = [
    "advance_upload",
    "cancel_requested",
    "cancel_unclaimed",
    "claim_job",
    "claim_tile",
    "delete_upload",
    "end_tiled_job",
    "fail_lost",
    "fail_unclaimed",
    "fan_out",
    "find_idempotent_job",
    "finish_job",
    "finish_merge",
    "finish_tile",
    "get_owned",
    "get_scene",
    "job_queue",
    "job_slots",
    "list_owned",
    "live_job_slots",
    "live_jobs",
    "lock_tenant",
    "read_job_row",
    "record_results",
    "release_job",
    "release_tile",
    "request_cancel",
    "reserved_upload_bytes",
    "set_upload_state",
    "stale_cutoff",
    "stale_uploads",
    "stored_bytes",
    "tile_rows",
    "undispatched_jobs",
    "undispatched_tiles",
    "update_running",
    "update_tile_running",
]
