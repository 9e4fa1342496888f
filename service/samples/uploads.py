"""A built sample actor directory as the canonical uploads of :mod:`service.store.actors`
(what the tests, the demo and the CLI upload)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from service.samples import dataset
from service.store.actors import clip_npz, layout_json, neutral_npz


def sample_actor_uploads(actor_dir: str | Path, names: Sequence[str] | None = None
                         ) -> tuple[bytes, bytes, dict[str, bytes]]:
    """A built sample actor directory (``facesynth sample-actor``) as canonical uploads.

    Parameters
    ----------
    actor_dir : the sample actor's directory
    names : performance names to include (default: every performance)

    Returns
    -------
    neutral : bytes               :func:`~service.store.actors.neutral_npz` with the sample actor's regions
    layout : bytes                :func:`~service.store.actors.layout_json`
    clips : {name: bytes}         :func:`~service.store.actors.clip_npz` per performance, the displacement made
                                  relative to the clip's vertices (maps only where every
                                  frame has them, as :func:`~service.samples.dataset.load_clip`)
    """
    actor = dataset.load_actor(actor_dir)
    neutral = neutral_npz(actor.vertices, actor.faces, actor.uv, actor.uv_faces, actor.regions)
    layout = layout_json(actor.marker_names, actor.marker_triangle, actor.marker_barycentric)
    clips = {}
    for name in (dataset.performance_names(actor_dir) if names is None else names):
        clip = dataset.load_clip(actor_dir, name, actor)
        clips[name] = clip_npz(clip.vertices, clip.markers, displacement=clip.displacement,
                               albedo=clip.albedo, fps=clip.fps)
    return neutral, layout, clips
