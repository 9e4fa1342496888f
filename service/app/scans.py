"""Scans and scan correspondence: the upload of a scan as UV-space maps, its records, and
the ``correspond`` job that brings one scan into another's UV space (issue 20; Vuvuzela,
digital_ira_course2014, :mod:`service.methods.correspondence`).

A scan is an ``.npz`` of (H,W) images in one UV layout: ``albedo`` (H,W,3) float (the
diffuse texture the correspondence is computed on) and ``position`` (H,W,3) float (the
point cloud in UV space, in the actor's unit) are required; ``specular`` (H,W,3),
``normal`` (H,W,3) float and ``mask`` (H,W) bool (the covered texels) are optional. It is
read with the bounded NPZ reader (:class:`~service.app.uploads.NpzUpload`: headers checked
before any data is decompressed), checked for finite values on the covered texels (NaN or
infinite values outside ``mask`` become 0), and stored canonically (float32 maps, bool
mask) as one blob under the actor's prefix.

The ``correspond`` job's payload (:mod:`service.jobs.tasks.correspond`) is ``{"source_scan_id",
"target_scan_id", "landmarks": [[[u_s, v_s], [u_t, v_t]], ...], "pinned": [...], "params":
{CorrespondenceParams}, "artist_uv": bool}``.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

import numpy as np
from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field

from models_store.schema import Scan as ScanRow
from models_store import registry
from service.app import schemas
from service.app.operations import submit
from service.app.services import Services, Submit
from service.app.uploads import ArraySpec, NpzUpload, npz_limit
from service.config import Settings
from service.errors import Conflict, InvalidInput
from service.io.npz import npz_bytes
from service.methods.correspondence.params import CorrespondenceParams

#: the job kind of a correspondence (the task of :mod:`service.jobs.tasks.correspond`)
CORRESPOND_JOB = "correspond"
#: the maps a scan may hold; ``albedo`` and ``position`` are required
SCAN_SPECS = {
    "albedo": ArraySpec(("H", "W", 3), "f"),
    "position": ArraySpec(("H", "W", 3), "f"),
    "specular": ArraySpec(("H", "W", 3), "f", False),
    "normal": ArraySpec(("H", "W", 3), "f", False),
    "mask": ArraySpec(("H", "W"), "b", False),
}
#: the optional coverage entry (not a map that is warped)
MASK = "mask"
#: bounds on the texels per side of a scan's maps (the flow needs at least 8)
MIN_SIDE, MAX_SIDE = 8, 8192
#: bound on the landmarks of one correspondence job
MAX_LANDMARKS = 4096

_SCAN_ID = "scn_01jb3k7y4b6d8f0h2k4m6p8r0t"
_ACTOR_ID = "act_01jb3k5q8m2v7c4x6b1n0r8tea"


# ---------------------------------------------------------------------------- schemas
class Scan(BaseModel):
    """A stored scan: its maps' names and size."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "scan_id": _SCAN_ID, "actor_id": _ACTOR_ID, "name": "smile", "width": 1024,
        "height": 1024, "maps": ["albedo", "mask", "position"], "size_bytes": 26000000,
        "created_at": "2025-01-15T09:30:00Z"}]})

    scan_id: str = Field(validation_alias="id")
    actor_id: str
    name: str | None
    width: int = Field(description="Texels per row of every map.")
    height: int = Field(description="Texels per column of every map.")
    maps: list[str] = Field(description="The arrays the scan holds (`mask` is its coverage).")
    size_bytes: int
    created_at: datetime


class ScanList(schemas.Items):
    items: list[Scan]


UV = Annotated[float, Field(ge=0.0, le=1.0)]
#: one landmark: [[u_s, v_s], [u_t, v_t]] in the unit UV tile of the source and the target
Landmark = Annotated[list[Annotated[list[UV], Len(2, 2)]], Len(2, 2)]


class CorrespondenceJob(BaseModel):
    """A correspondence job: warp the source scan into the target scan's UV space."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "source_scan_id": _SCAN_ID, "target_scan_id": "scn_01jb3k7y4b6d8f0h2k4m6p8r0v",
        "landmarks": [[[0.31, 0.52], [0.30, 0.50]], [[0.69, 0.52], [0.70, 0.51]],
                      [[0.50, 0.30], [0.50, 0.31]]],
        "pinned": [0], "artist_uv": False}]})

    source_scan_id: str = Field(description="The scan to warp (e.g. an expression).")
    target_scan_id: str = Field(description="The scan whose UV space the result is in "
                                            "(e.g. the neutral).")
    landmarks: Annotated[list[Landmark], Len(3, MAX_LANDMARKS)] = Field(
        description="Clicked corresponding points `[[u_s, v_s], [u_t, v_t]]`, unit-tile UV "
                    "coordinates in the source and the target (at least 3: the Delaunay "
                    "pre-warp needs a triangle).")
    pinned: list[Annotated[int, Field(ge=0)]] = Field(
        default_factory=list, description="Indices of landmarks that are pinned (drawn as "
                                          "black dots in both flow textures).")
    params: CorrespondenceParams = Field(default_factory=CorrespondenceParams,
                                         description="Correspondence parameters.")
    artist_uv: bool = Field(False, description="The actor's neutral mesh has the target "
                            "scan's UV layout: also store the blendshape (the neutral's "
                            "vertices looked up in the warped position map).")


# ---------------------------------------------------------------------------- uploads
def parse_scan(data: bytes, settings: Settings) -> tuple[bytes, int, int, list[str]]:
    """Validate a scan upload: (canonical NPZ bytes, width, height, map names).

    Raises
    ------
    FormatError (422)   not an NPZ, a missing ``albedo``/``position``, wrong shapes or dtypes
    SizeLimitError (413) more decompressed data than the limit
    InvalidInput (422)  maps of different sizes, non-finite values, too small or large, an
                        empty mask
    """
    upload = NpzUpload(data, SCAN_SPECS, npz_limit(settings), what="scan")
    H, W = upload.dims["H"], upload.dims["W"]
    if not (MIN_SIDE <= H <= MAX_SIDE and MIN_SIDE <= W <= MAX_SIDE):
        raise InvalidInput(f"the scan's maps are {H}×{W} texels; each side must be in "
                           f"[{MIN_SIDE}, {MAX_SIDE}]")
    arrays = upload.load()
    canonical = {}
    mask = arrays.get(MASK)
    if mask is not None:
        if not mask.any():
            raise InvalidInput("the scan's 'mask' covers no texel")
        canonical[MASK] = mask = mask.astype(bool)
    for name, values in arrays.items():
        if name == MASK:
            continue
        finite = np.isfinite(values).all(axis=-1)
        if mask is not None:                  # uncovered texels may hold anything: zeroed
            values = np.where(finite[..., None] | mask[..., None], values, 0.0)
            finite |= ~mask
        if not finite.all():
            bad = np.argwhere(~finite)
            where = "covered texels" if mask is not None else "texels"
            raise InvalidInput(f"the scan's '{name}' has {len(bad)} {where} with NaN or "
                               f"infinite values (first at row {bad[0][0]}, column "
                               f"{bad[0][1]}); values must be finite where 'mask' is true "
                               "(without a mask: everywhere)")
        canonical[name] = values.astype(np.float32)
    if MASK not in canonical and not (canonical["albedo"] != 0).any():
        raise InvalidInput("the scan's 'albedo' is zero everywhere (no texel is covered)")
    return npz_bytes(**canonical), W, H, sorted(canonical)


# ---------------------------------------------------------------------------- operations
def add_scan(services: Services, actor_id: str, data: bytes, name: str | None) -> Scan:
    """Validate and store a scan of the actor."""
    with services.session() as session:
        registry.get_actor(session, actor_id)
    blob, width, height, maps = parse_scan(data, services.settings)
    with services.session() as session:
        row = registry.add_scan(session, services.blobs, actor_id, blob, width=width,
                                height=height, maps=maps, name=name)
        return Scan.model_validate(row)


def list_scans(services: Services, actor_id: str, page) -> ScanList:
    """The actor's scans, oldest first, one ``page`` (``service.api.query.Page``) of them."""
    with services.session() as session:
        rows, cursor = page.rows(registry.list_scans(session, actor_id, **page.fetch(ScanRow)))
        return ScanList(items=[Scan.model_validate(s) for s in rows], next_cursor=cursor)


def get_scan(services: Services, actor_id: str, scan_id: str) -> Scan:
    """One scan of the actor (404 for another actor's)."""
    with services.session() as session:
        registry.get_actor(session, actor_id)
        return Scan.model_validate(registry.get_scan(session, scan_id, actor_id))


def delete_scan(services: Services, actor_id: str, scan_id: str) -> None:
    """Delete a scan of the actor and its blob."""
    with services.session() as session:
        registry.get_actor(session, actor_id)
        registry.delete_scan(session, services.blobs, scan_id, actor_id)


def submit_correspondence(services: Services, submit_job: Submit, actor_id: str,
                          request: CorrespondenceJob) -> schemas.JobAccepted:
    """Check a correspondence request against the stored scans and queue its job.

    Raises
    ------
    NotFound      unknown actor, an unknown scan or one of another actor
    InvalidInput  the scans hold different maps, a pinned index past the landmarks, or
                  ``artist_uv`` with a neutral without UVs
    Conflict      ``artist_uv`` and the actor has no neutral
    """
    n = len(request.landmarks)
    if request.pinned and max(request.pinned) >= n:
        raise InvalidInput(f"pinned landmark {max(request.pinned)} does not exist; there are "
                           f"{n} landmarks (indices 0..{n - 1})")
    with services.session() as session:
        actor = registry.get_actor(session, actor_id)
        source = registry.get_scan(session, request.source_scan_id, actor_id)
        target = registry.get_scan(session, request.target_scan_id, actor_id)
        src_maps, tgt_maps = set(source.maps) - {MASK}, set(target.maps) - {MASK}
        if src_maps != tgt_maps:
            raise InvalidInput(f"the scans hold different maps: source {sorted(src_maps)}, "
                               f"target {sorted(tgt_maps)}; the warped maps must match the "
                               "target's (upload both with the same maps)")
        if request.artist_uv:
            if actor.neutral_blob is None:
                raise Conflict(f"artist_uv needs the actor's neutral; PUT "
                               f"/v1/actors/{actor_id}/neutral first")
            if actor.vertex_count is None:
                raise InvalidInput("the actor's neutral has no vertices")
        job = registry.create_job(session, CORRESPOND_JOB, actor_id,
                                  payload=request.model_dump(mode="json"))
        submit(session, submit_job, job)
    return schemas.JobAccepted(job_id=job.id)
