"""A stress-blend model on disk: ``manifest.json`` + ``model.npz`` + the scans' maps as EXR.

* ``displacement.exr``  channels ``s0 … s<K>``: each scan's displacement map (scan 0 the
  neutral), mm along the normal, relative to the scan's mesh;
* ``albedo.exr``        channels ``s<k>.R``, ``s<k>.G``, ``s<k>.B`` (if trained with albedo);
* ``masks.exr``         channels ``m0 … m<R-1>``: the wrinkle-region masks at the
  displacement resolution, for engines (not read back; ``model.npz`` holds them per vertex);
* ``model.npz``         neutral, faces, UV layout, the scans' local stresses (float64, so a
  frame equal to a scan reproduces it exactly after a reload), masks, importance;
* ``manifest.json``     kind, format version, params, metrics, scan names, sha256 of every file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.io.atomic import sha256_file, write_bytes, write_npz
from service.io.exr import read_exr, write_exr
from service.io.npz import npz_arrays
from service.methods.model_dir import ModelCorrupt, read_model_files
from service.methods.stress_blend.data import StressBlendData
from service.methods.stress_blend.params import StressBlendParams

KIND = "stress_blend"
FORMAT_VERSION = 1


def write_model(model: StressBlendData, texel_masks: np.ndarray, path) -> dict:
    """Write a model's stored data ``model`` and its region masks at the displacement
    resolution ``texel_masks`` (R,H,H) (for engines) into directory ``path`` (created);
    returns the manifest."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    files = {}
    write_exr(path / "displacement.exr", {f"s{k}": m for k, m in enumerate(model.displacement)})
    files["displacement.exr"] = sha256_file(path / "displacement.exr")
    if model.albedo is not None:
        write_exr(path / "albedo.exr", {f"s{k}.{c}": m[..., i] for k, m in enumerate(model.albedo)
                                        for i, c in enumerate("RGB")})
        files["albedo.exr"] = sha256_file(path / "albedo.exr")
    write_exr(path / "masks.exr", {f"m{r}": m for r, m in enumerate(texel_masks)})
    files["masks.exr"] = sha256_file(path / "masks.exr")
    files["model.npz"] = write_npz(path / "model.npz", {
        "neutral": model.neutral, "faces": model.faces, "uv": model.uv, "uv_faces": model.uv_faces,
        "scan_stress": model.scan_stress, "masks": model.masks, "importance": model.importance})
    manifest = {"kind": KIND, "format_version": FORMAT_VERSION, "params": model.params.model_dump(),
                "scans": list(model.scan_names), "metrics": model.metrics, "files": files,
                "size_bytes": sum((path / f).stat().st_size for f in files)}
    write_bytes(path / "manifest.json", json.dumps(manifest, indent=1).encode())
    return manifest


def read_model(path) -> StressBlendData:
    """The stored data written by :func:`write_model` in ``path`` (checksums verified first)."""
    # the path as given: a verified directory's digests (models_store.blobs.VerifiedDir)
    manifest, data = read_model_files(path, KIND, FORMAT_VERSION, required=("model.npz", "displacement.exr"))
    path = Path(path)
    params = StressBlendParams.model_validate(manifest["params"])
    a = npz_arrays(data["model.npz"])
    S = len(a["scan_stress"])
    try:
        ch = read_exr(data["displacement.exr"])
        disp = np.stack([ch[f"s{k}"] for k in range(S)])
        alb = None
        if "albedo.exr" in data:
            ch = read_exr(data["albedo.exr"])
            alb = np.stack([np.stack([ch[f"s{k}.{c}"] for c in "RGB"], axis=-1) for k in range(S)])
    except KeyError as e:
        raise ModelCorrupt(f"{path}: a map lacks channel {e}") from None
    return StressBlendData(params=params, neutral=a["neutral"], faces=a["faces"], uv=a["uv"],
                           uv_faces=a["uv_faces"], scan_names=list(manifest["scans"]),
                           scan_stress=a["scan_stress"], displacement=disp, albedo=alb,
                           masks=a["masks"], importance=a["importance"], metrics=manifest["metrics"])
