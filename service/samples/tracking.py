"""A rendered performance for performance-flow tracking, built from a sample actor directory.

fyffe (digital_ira_course2014, "Driving High-Resolution Facial Scans with Video Performance
Capture") §3 inputs: an artist mesh of the neutral, static scans whose raw geometry is NOT
in correspondence with it (each with one image per camera view), calibrated cameras, and the
performance as frames per view. :func:`build_tracking_sample` makes all of it from an
existing actor directory (family a or b, any level) and keeps the ground truth beside it:

* **artist mesh**: the actor's ``neutral.npz`` (vertices, faces, UVs, regions);
* **static scans**: the neutral plus the peak frame of every training clip (or the ones
  named); the raw geometry of each is *re-meshed* as a range scan — the scan camera's
  z-buffer sampled on a pixel grid, triangulated where neighbouring samples are depth
  continuous, with 0.05 mm depth noise — so its vertices share nothing with the artist
  mesh; ground truth on the artist topology in ``scan_truth``;
* **images**: the posed ground-truth meshes rendered through :func:`face_cameras`
  (frontal view first, so ``views=1`` is the monocular case), textured with the clip's
  albedo map (its wrinkle and blood-flow changes) times a fixed seeded skin texture in UV
  space (multi-scale noise and small spots: the renders' own albedo maps carry too little
  texture at camera resolution for any optical flow, real skin does), Lambert-shaded;
* **shading changes and camera noise** in the performance: the light direction swings
  ±``light_swing_deg`` and the exposure ±6 % over the performance, Gaussian noise of
  ``noise`` 8-bit levels per pixel (the static scans are lit by the fixed scan light);
* **maps**: each static scan's albedo and displacement map (for the per-frame blended
  maps of §7.3) and the performance's ground-truth maps where it has them.

Images are stored as 8-bit luminance (sRGB-encoded), (…,C,H,W) uint8: the tracking's flows
work on one channel, and 154 frames × 3 views of RGB at 512² would be 360 MB.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields
from pathlib import Path

import cv2
import numpy as np

from service.geometry.camera import Camera, rasterize
from service.io.atomic import write_npz
from service.samples.render import face_cameras, shade_textured

#: the static scans' light (toward the light, world) and the performance's mean light
SCAN_LIGHT = (0.3, 0.5, 1.0)
#: the performance that is tracked (in every family)
PERFORMANCE = "heldout_in_range"
#: texels of the skin texture (the albedo map is upsampled to it)
TEXTURE_SIZE = 1024
#: camera arc of the views, degrees of yaw (frontal first: views=1 is monocular)
YAWS = (0.0, -30.0, 30.0)


@dataclass
class TrackingSample:
    """Inputs and ground truth of a rendered performance (world coordinates, mm).

    Attributes
    ----------
    artist_vertices : (n,3) float   the artist (neutral) mesh, head frame = world
    faces : (m,3) int;  uv : (u,2);  uv_faces : (m,3);  region : (n,) int (0 = face)
    cameras : list[Camera]          C calibrated views (the same for scans and performance)
    scan_names : (S,) str           static scans, scan 0 the neutral
    scan_images : (S,C,H,W) uint8   one image per view per scan
    scan_vertices : list of (k_s,3) float   raw re-meshed scan geometry (world)
    scan_faces : list of (l_s,3) int
    scan_truth : (S,n,3) float      the scans' ground truth on the artist topology (world)
    scan_albedo : (S,h,w,3) float16, scan_displacement : (S,H',W') float32   their maps
    frame_images : (T,C,H,W) uint8  the performance per view
    frame_truth : (T,n,3) float     its ground truth (world)
    truth_map_frames : (k,) int, truth_albedo : (k,h,w,3) float16   ground-truth maps
    fps : float
    """

    artist_vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    region: np.ndarray
    cameras: list
    scan_names: np.ndarray
    scan_images: np.ndarray
    scan_vertices: list
    scan_faces: list
    scan_truth: np.ndarray
    scan_albedo: np.ndarray
    scan_displacement: np.ndarray
    frame_images: np.ndarray
    frame_truth: np.ndarray
    truth_map_frames: np.ndarray
    truth_albedo: np.ndarray
    fps: float
    info: dict = field(default_factory=dict)

    def save(self, path: str | Path) -> str:
        """Write one ``.npz`` (ragged scans concatenated with offsets); returns its sha256."""
        arrays = {f.name: getattr(self, f.name) for f in fields(self)
                  if f.name not in ("cameras", "scan_vertices", "scan_faces", "info", "fps")}
        arrays["cameras"] = np.array(json.dumps([c.to_json() for c in self.cameras]))
        arrays["info"] = np.array(json.dumps(self.info))
        arrays["fps"] = np.float64(self.fps)
        arrays["scan_vertex_counts"] = np.array([len(v) for v in self.scan_vertices])
        arrays["scan_face_counts"] = np.array([len(f) for f in self.scan_faces])
        arrays["scan_vertices"] = np.concatenate(self.scan_vertices).astype(np.float32)
        arrays["scan_faces"] = np.concatenate(self.scan_faces).astype(np.int32)
        return write_npz(path, arrays)

    @classmethod
    def load(cls, path: str | Path) -> "TrackingSample":
        with np.load(path) as d:
            a = {k: d[k] for k in d.files}
        vsplit = np.cumsum(a.pop("scan_vertex_counts"))[:-1]
        fsplit = np.cumsum(a.pop("scan_face_counts"))[:-1]
        a["scan_vertices"] = [v.astype(np.float64) for v in np.split(a["scan_vertices"], vsplit)]
        a["scan_faces"] = [f.astype(np.int64) for f in np.split(a["scan_faces"], fsplit)]
        a["cameras"] = [Camera.from_json(c) for c in json.loads(str(a["cameras"]))]
        a["info"] = json.loads(str(a["info"]))
        a["fps"] = float(a["fps"])
        return cls(**a)


def skin_texture(seed: int, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A fixed multiplicative skin texture (size,size) float32 around 1, seeded.

    Band-limited noise at 1.5, 4 and 10 texels (σ of the Gaussian filter; ±~12 % in all)
    plus ~1500 small dark spots (moles, pores at camera scale), in UV space so it moves
    with the skin.
    """
    rng = np.random.default_rng([seed, 1901])
    tex = np.zeros((size, size), np.float32)
    for sigma, amp in ((1.5, 0.05), (4.0, 0.06), (10.0, 0.06)):
        n = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        tex += amp * n / max(float(n.std()), 1e-9)
    spots = np.zeros((size, size), np.float32)
    ij = rng.integers(0, size, (size * size // 700, 2))
    spots[ij[:, 0], ij[:, 1]] = rng.uniform(0.5, 1.0, len(ij))
    spots = cv2.GaussianBlur(spots, (0, 0), 1.6) * 2 * np.pi * 1.6 ** 2
    return np.clip(1.0 + tex - 0.35 * spots, 0.4, 1.6)


def range_scan(camera: Camera, V: np.ndarray, F: np.ndarray, grid: int, seed: int,
               max_step_mm: float = 4.0, noise_mm: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Re-mesh a surface as a range scan: z-buffer samples on a pixel grid, triangulated.

    The mesh is rasterized through ``camera`` resized to ``grid`` pixels; every covered
    pixel becomes a vertex at the surface point it sees (plus Gaussian depth noise along
    the view ray), and each 2×2 block of covered pixels whose depths differ by at most
    ``max_step_mm`` two triangles. The vertices share nothing with the input mesh's.

    Returns
    -------
    vertices : (k,3) float, faces : (l,3) int   (counter-clockwise seen from the camera)
    """
    cam = camera.scaled(grid / camera.width)
    triangle, bary = rasterize(cam, V, F)
    H, W = triangle.shape
    fg = triangle >= 0
    P = np.einsum("pk,pkd->pd", bary[fg], V[F[triangle[fg]]])
    rng = np.random.default_rng([seed, 1902])
    ray = P - cam.centre
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    P = P + rng.normal(0.0, noise_mm, (len(P), 1)) * ray
    index = np.full((H, W), -1)
    index[fg] = np.arange(len(P))
    depth = np.full((H, W), np.inf)
    depth[fg] = cam.project(P)[:, 2]
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    za, zb, zc, zd = depth[:-1, :-1], depth[:-1, 1:], depth[1:, :-1], depth[1:, 1:]
    z = np.stack([za, zb, zc, zd])
    ok = (np.stack([a, b, c, d]) >= 0).all(axis=0) & (np.ptp(np.where(np.isfinite(z), z, 0), axis=0) <= max_step_mm)
    # image rows go down: (a, c, b) is counter-clockwise in the world seen from the camera
    faces = np.concatenate([np.stack([a[ok], c[ok], b[ok]], 1), np.stack([b[ok], c[ok], d[ok]], 1)])
    used = np.unique(faces)
    remap = np.full(len(P), -1)
    remap[used] = np.arange(len(used))
    return P[used], remap[faces]


def _luminance8(linear: np.ndarray, gain: float, noise: float, rng) -> np.ndarray:
    """Linear RGB (H,W,3) → noisy 8-bit sRGB-encoded luminance (H,W)."""
    y = np.clip(gain * linear @ np.array([0.2126, 0.7152, 0.0722]), 0, 1)
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055) * 255
    return np.clip(np.rint(srgb + rng.normal(0.0, noise, srgb.shape)), 0, 255).astype(np.uint8)


def _light(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    base = np.asarray(SCAN_LIGHT, float)
    a, p = np.radians(yaw_deg), np.radians(pitch_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    return Rx @ Ry @ base


def build_tracking_sample(actor_dir: str | Path, size: int = 512, frames: int | None = None,
                          views: int = 3, scans: tuple[str, ...] | None = None,
                          scan_grid: int = 256, noise: float = 1.0,
                          light_swing_deg: float = 20.0, field_mm: float = 230.0,
                          seed: int = 1, workers: int = 2, rest_frames: int = 0,
                          out: str | Path | None = None) -> TrackingSample:
    """Render a performance and static scans for tracking from a sample actor directory.

    Parameters
    ----------
    actor_dir : a built sample actor (``manifest.json`` present), family a or b, in mm
    size : image width = height, pixels
    frames : the first ``frames`` of the performance (default all: 154 in a, 146 in b)
    views : 1 to 3 cameras (frontal first)
    scans : training clips whose peak frame is a static scan (default all); the neutral is
            always scan 0
    scan_grid : pixels of the range-scan grid (the raw scans' resolution)
    noise : camera noise σ, 8-bit levels;  light_swing_deg : the light's swing over time
    field_mm : the width of the scene the cameras see at the face
    rest_frames : frames appended after the last one with its pose held (light, exposure
                  and camera noise go on): a whole performance ends on the neutral, so with
                  a rest the take starts and ends at rest and a drift test compares the
                  same expression at both ends
    out : also write the sample to this ``.npz``

    Returns
    -------
    TrackingSample
    """
    actor_dir = Path(actor_dir)
    manifest = json.loads((actor_dir / "manifest.json").read_text())
    if manifest.get("units", "mm") != "mm":
        raise ValueError("tracking samples are rendered with mm cameras: the actor must be in mm")
    if not 1 <= views <= len(YAWS):
        raise ValueError(f"views must be 1..{len(YAWS)}, got {views}")
    with np.load(actor_dir / "neutral.npz") as d:
        V0, F = d["vertices"].astype(np.float64), d["faces"].astype(np.int64)
        uv, uvf, region = d["uv"].astype(np.float64), d["uv_faces"].astype(np.int64), d["region"]
    training = sorted(k for k, v in manifest["performances"].items() if v["kind"] == "training")
    scans = tuple(training if scans is None else scans)
    unknown = set(scans) - set(training)
    if unknown:
        raise ValueError(f"unknown training clips {sorted(unknown)}; known: {training}")

    centre = V0[region == 0].mean(axis=0)
    cams = face_cameras(centre, size=size, yaws_deg=YAWS[:views], field_mm=field_mm)
    texture = skin_texture(seed)

    def textured(albedo_map):
        alb = cv2.resize(np.asarray(albedo_map, np.float32), (TEXTURE_SIZE, TEXTURE_SIZE),
                         interpolation=cv2.INTER_LINEAR)
        return alb * texture[..., None]

    # static scans: the neutral and each clip's peak frame, with its maps
    names, truth, albedo, disp = ["neutral"], [V0], [], []
    for k, clip in enumerate(scans):
        with np.load(actor_dir / "performances" / f"{clip}.npz") as d:
            peak = int(np.argmax(d["weights"].sum(axis=1)))
            slot = {int(f): i for i, f in enumerate(d["map_frames"])}
            if k == 0:
                albedo.append(d["albedo"][slot[0]]), disp.append(d["displacement"][slot[0]])
            names.append(clip)
            truth.append(d["vertices"][peak].astype(np.float64))
            albedo.append(d["albedo"][slot[peak]]), disp.append(d["displacement"][slot[peak]])
    with np.load(actor_dir / "performances" / f"{PERFORMANCE}.npz") as d:
        T = d["vertices"].shape[0] if frames is None else min(int(frames), d["vertices"].shape[0])
        frame_truth = d["vertices"][:T].astype(np.float64)
        map_frames = d["map_frames"].astype(np.int64)
        perf_albedo = d["albedo"]
    keep = map_frames < T
    if rest_frames:
        frame_truth = np.concatenate([frame_truth, np.repeat(frame_truth[-1:], rest_frames, 0)])
        T += int(rest_frames)

    def render_scan(s):
        tex = textured(albedo[s])
        return np.stack([_luminance8(shade_textured(c, truth[s], F, uv, uvf, tex, SCAN_LIGHT), 1.0,
                                     noise, np.random.default_rng([seed, 1904, s, i]))
                         for i, c in enumerate(cams)])

    def render_frame(t):
        j = np.searchsorted(map_frames, t, side="right") - 1
        j1 = min(j + 1, len(map_frames) - 1)
        span = max(map_frames[j1] - map_frames[j], 1)
        a = (t - map_frames[j]) / span if j1 != j else 0.0
        tex = textured((1 - a) * perf_albedo[j].astype(np.float32) + a * perf_albedo[j1].astype(np.float32))
        phase = 2 * np.pi * t / max(T, 1)
        light = _light(light_swing_deg * np.sin(phase), 0.4 * light_swing_deg * np.sin(2 * phase))
        gain = 1.0 + 0.06 * np.sin(1.3 * phase + 0.5)
        return np.stack([_luminance8(shade_textured(c, frame_truth[t], F, uv, uvf, tex, light), gain,
                                     noise, np.random.default_rng([seed, 1905, t, i]))
                         for i, c in enumerate(cams)])

    with ThreadPoolExecutor(workers) as pool:            # NumPy / OpenCV release the GIL
        scan_images = np.stack(list(pool.map(render_scan, range(len(names)))))
        frame_images = np.stack(list(pool.map(render_frame, range(T))))
    raw = [range_scan(cams[0], truth[s], F, scan_grid, seed + 31 * s) for s in range(len(names))]
    sample = TrackingSample(
        artist_vertices=V0, faces=F, uv=uv, uv_faces=uvf, region=region.astype(np.int64),
        cameras=cams, scan_names=np.array(names), scan_images=scan_images,
        scan_vertices=[r[0] for r in raw], scan_faces=[r[1] for r in raw],
        scan_truth=np.stack(truth), scan_albedo=np.stack(albedo).astype(np.float16),
        scan_displacement=np.stack(disp).astype(np.float32), frame_images=frame_images,
        frame_truth=frame_truth, truth_map_frames=map_frames[keep],
        truth_albedo=perf_albedo[keep].astype(np.float16), fps=float(manifest["fps"]),
        info={"actor": str(actor_dir), "family": manifest.get("family", "a"), "size": size,
              "views": views, "frames": T, "rest_frames": int(rest_frames), "noise": noise,
              "light_swing_deg": light_swing_deg,
              "scan_grid": scan_grid, "seed": seed})
    if out is not None:
        sample.save(out)
    return sample

