"""The API's fixed limits and tolerances, named in one place.

The limits an operator tunes are :class:`service.config.Settings` fields
(``max_body_bytes``, ``max_frames_per_request``, ``max_map_resolution``, ``max_vertices``);
these are the ones that follow from them or that no deployment needs to change.
"""

from __future__ import annotations

#: an uploaded NPZ may decompress to at most this many times the body limit (zip bombs)
NPZ_EXPANSION = 4
#: most arrays an uploaded NPZ may hold
NPZ_MAX_MEMBERS = 64
#: most triangles per vertex an uploaded mesh may declare (a closed mesh has ~2)
FACES_PER_VERTEX = 4
#: most per-frame files in one multipart clip upload
MULTIPART_MAX_FILES = 10_000
#: largest non-file field of a multipart upload (e.g. the landmarks JSON), bytes
MULTIPART_MAX_FIELD_BYTES = 1 << 20
#: largest JSON ``metadata`` of an actor, bytes when serialized
METADATA_MAX_BYTES = 64 << 10
#: a triangle whose area is at most this times its longest edge squared is degenerate
DEGENERATE_AREA_RTOL = 1e-12
#: synchronous syntheses running at once; one more is answered 503 with Retry-After
MAX_CONCURRENT_SYNTHESES = 2
#: default longest wait of a synchronous synthesis for a slot, seconds (setting
#: ``synthesis_queue_seconds``)
SYNTHESIS_WAIT_SECONDS = 30.0
#: default most synchronous syntheses waiting for a slot (setting ``synthesis_queue_depth``)
SYNTHESIS_QUEUE_DEPTH = 64
#: seconds a client is asked to wait after a 503
RETRY_AFTER_SECONDS = 1
#: how often the job event stream polls the database, seconds
EVENTS_POLL_SECONDS = 0.5
#: a comment line is sent on an idle event stream this often, seconds (keeps proxies open)
EVENTS_KEEPALIVE_SECONDS = 15.0
#: the longest accepted ``X-Request-ID``; longer or unsafe ones are replaced
REQUEST_ID_MAX_LENGTH = 128
#: bytes of loaded input-rig registrations kept in memory (a level-1 actor's is ~5 MB)
REGISTRATION_CACHE_BYTES = 256 << 20
