"""A picture gallery of a built sample actor: shaded meshes under grazing light, and maps.

``write_gallery(actor_dir, out_dir)`` reads what :func:`service.samples.actor.build_sample_actor`
wrote and writes three PNGs:

    shaded.png   ground truth (top row) and the same frames without fine detail (bottom
                 row) at neutral and the peaks of brow raise, brow furrow, smile and squint,
                 grey albedo, light grazing from above so that furrows cast their shading
    maps.png     displacement maps (mm, diverging colours) of the face tile at the same
                 frames, with a 4× close-up of the forehead where pores and wrinkles meet
    albedo.png   albedo maps at neutral, smile and squint with 4× close-ups of the left
                 eye and cheek (blood-flow redness, pores, speckle)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.samples.render import Camera, face_cameras, shade, to_srgb8, write_png
from service.samples.rig import load_ict_rig

FRAMES = (("neutral", "train_brow_raise", "first"), ("brow raise", "train_brow_raise", "peak"),
          ("brow furrow", "train_brow_furrow", "peak"), ("smile", "train_smile", "peak"),
          ("squint", "train_squint", "peak"))
GRAZING_LIGHT = (0.15, 1.0, 0.45)       # from above the forehead, ~24° above the face plane
SIZE = 480                              # shaded renders, pixels
PANEL = 512                             # map panels, pixels


def _frame(actor: Path, performance: str, which: str) -> dict[str, np.ndarray]:
    """One frame's meshes and maps (each array of the file read once, for that frame only)."""
    with np.load(actor / "performances" / f"{performance}.npz") as data:
        f = 0 if which == "first" else int(np.argmax(data["weights"].sum(axis=1)))
        slot = int(np.flatnonzero(data["map_frames"] == f)[0])
        return {"vertices": data["vertices"][f], "vertices_medium": data["vertices_medium"][f],
                "displacement": data["displacement"][slot],
                "albedo": data["albedo"][slot].astype(np.float32)}


def front_camera(V: np.ndarray, size: int) -> Camera:
    """A camera 600 mm in front of the face (V (n,3), mm), framing its upper 80 %."""
    centre = np.array([np.median(V[:, 0]), np.percentile(V[:, 1], 70), V[:, 2].max()])
    return face_cameras(centre, distance=600.0, size=size, yaws_deg=(0.0,), field_mm=190.0)[0]


def _diverging(x: np.ndarray, limit: float) -> np.ndarray:
    """Blue (negative) – white – red (positive) colours (…,3) in [0,1] for x in ±limit."""
    t = np.clip(x / limit, -1, 1)[..., None]
    white, red, blue = np.ones(3), np.array([0.70, 0.05, 0.05]), np.array([0.05, 0.20, 0.70])
    return np.where(t > 0, white + t * (red - white), white - t * (blue - white))


def _resize(image: np.ndarray, size: int) -> np.ndarray:
    """Area-resample an (h,w) or (h,w,3) float image to (size,size) (box filter)."""
    from PIL import Image

    channels = image[..., None] if image.ndim == 2 else image
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(channels[..., k], np.float32))
                               .resize((size, size), Image.BOX)) for k in range(channels.shape[-1])], -1)
    return out[..., 0] if image.ndim == 2 else out


def caption(image: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    img = Image.fromarray(image)
    ImageDraw.Draw(img).text((8, 6), text, fill=(255, 255, 255) if image.mean() < 128 else (0, 0, 0))
    return np.asarray(img)


def write_gallery(actor_dir: str | Path, out_dir: str | Path) -> list[Path]:
    """Render the gallery of the actor in ``actor_dir`` into ``out_dir``; return the PNG paths."""
    actor, out = Path(actor_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    neutral = np.load(actor / "neutral.npz")
    faces, uv, uv_faces = neutral["faces"], neutral["uv"], neutral["uv_faces"]
    cam = front_camera(neutral["vertices"], SIZE)
    grey = np.full((len(neutral["vertices"]), 3), 0.6)

    frames = [(label, _frame(actor, perf, which)) for label, perf, which in FRAMES]
    rows = []
    for key in ("vertices", "vertices_medium"):
        rows.append(np.concatenate([
            caption(to_srgb8(shade(cam, data[key], faces, grey, light_dir=GRAZING_LIGHT,
                                  ambient=0.05)), f"{label} ({'detail' if key == 'vertices' else 'no detail'})")
            for label, data in frames], axis=1))
    paths = [out / "shaded.png"]
    write_png(paths[-1], np.concatenate(rows, axis=0))

    # close-up centres: UV of the vertex nearest a landmark-relative point (in family a the
    # rig's vertices come first in the subdivided mesh, so rig landmark ids index V too;
    # other families keep the rig's neutral in rig_vertices)
    V = neutral["vertices"]
    manifest = json.loads((actor / "manifest.json").read_text()) if (actor / "manifest.json").is_file() else {}
    lm = (V if manifest.get("family", "a") == "a" else neutral["rig_vertices"])[load_ict_rig().landmarks68]
    corner_uv = np.zeros((len(V), 2))
    corner_uv[faces.ravel()] = uv[uv_faces.ravel()]

    def uv_near(point):
        u, v = corner_uv[np.argmin(np.linalg.norm(V - point, axis=1))]
        return 1.0 - v, u                              # (row, column) as fractions

    forehead = uv_near((lm[19] + lm[24]) / 2 + [0, 28, 0])
    left_eye = uv_near(lm[45] + [6, -6, 0])

    def crop(image, centre, zoom):
        n = image.shape[0]
        h = n // (2 * zoom)
        r, c = (int(np.clip(centre[0] * n, h, n - h)), int(np.clip(centre[1] * n, h, n - h)))
        return _resize(image[r - h:r + h, c - h:c + h], PANEL)

    face_tile = lambda image: _resize(image[: int(0.8 * image.shape[0]), : int(0.8 * image.shape[1])], PANEL)
    maps = [np.concatenate([
        caption(to_srgb8(_diverging(face_tile(d), 1.0)), f"{label}: displacement (face tile), ±1 mm"),
        caption(to_srgb8(_diverging(crop(d, forehead, 4), 0.4)), "forehead ×4, ±0.4 mm")], axis=0)
        for label, data in frames for d in [data["displacement"]]]
    paths.append(out / "maps.png")
    write_png(paths[-1], np.concatenate(maps, axis=1))

    albedo = [np.concatenate([caption(to_srgb8(face_tile(a)), f"{label}: albedo (face tile)"),
                              caption(to_srgb8(crop(a, left_eye, 4)), "left eye and cheek ×4")], axis=0)
              for label, data in (frames[0], frames[3], frames[4]) for a in [data["albedo"]]]
    paths.append(out / "albedo.png")
    write_png(paths[-1], np.concatenate(albedo, axis=1))
    return paths
