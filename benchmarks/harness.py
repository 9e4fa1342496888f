"""What the benchmark reports share: the sample actor's data, fresh-process workers with
peak-memory measurement, the fine-detail metric at the map texels, the PDM baseline, and
figure helpers. Each report imports this module (``import harness``). Two reports still
reuse another report's cached model builds, whose workers live in that script:
``generalization_report`` (``shape_space_report``'s shape-space models) and
``game_outputs_report`` (``pdm_report``'s PDM models and figure layout).

Peak memory: a worker resets the resident-set high-water mark (``echo 5 >
/proc/self/clear_refs``) and reports ``VmHWM − VmRSS`` at the reset, the peak resident
memory the measured step added (C allocations included).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SEED, LEVEL = 1, 1                     # the default sample actor
HELDOUT = ("heldout_in_range", "heldout_out_of_range")
FACE = "face"                          # actor region of the main metrics
BASIC_OUTPUTS = ("mesh", "displacement")
NEUTRAL_CLIP = "train_brow_raise"      # its frame 0 gives the static neutral map
SCORED_REGIONS = (FACE, "narrow_face") # ... and the marker-covered part of it (region 0)
GT_ROW = "ground truth (mesh + relative map)"


def ensure_actor(actor_dir: Path, seed: int = SEED, level: int = LEVEL) -> None:
    """Build the sample actor (default level 1, seed 1) into ``actor_dir`` unless it is there."""
    if (actor_dir / "manifest.json").is_file():
        return
    from service.samples.actor import build_sample_actor

    print(f"building the sample actor into {actor_dir} (a few minutes)", file=sys.stderr)
    build_sample_actor(actor_dir, seed=seed, level=level)


def training_clips(actor_dir: Path, actor):
    from service.samples.dataset import load_clip, performance_names

    return [load_clip(actor_dir, name, actor) for name in performance_names(actor_dir, "train_")]


@dataclass
class Heldout:
    """Ground truth of one held-out performance at its evaluated map frames (world pose).

    frames (k,) frame numbers; vertices, medium (k,n,3) float64 mm; markers (k,M,3);
    displacement (k,H,H) float32 mm, all detail along the normal of ``medium``;
    strength (k,) sum of the expression weights (to pick strong frames).
    """

    name: str
    frames: np.ndarray
    vertices: np.ndarray
    medium: np.ndarray
    markers: np.ndarray
    displacement: np.ndarray
    strength: np.ndarray


def load_heldout(actor_dir: Path, name: str, limit: int | None) -> Heldout:
    """The map frames of a held-out performance (``limit``: that many, evenly spaced)."""
    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        mf = d["map_frames"].astype(np.int64)
        slots = np.arange(len(mf))
        if limit is not None and limit < len(mf):
            slots = np.unique(np.round(np.linspace(0, len(mf) - 1, limit)).astype(np.int64))
        f = mf[slots]
        return Heldout(name, f, d["vertices"][f].astype(np.float64),
                       d["vertices_medium"][f].astype(np.float64), d["markers"][f].astype(np.float64),
                       d["displacement"][slots].astype(np.float32), d["weights"][f].sum(axis=1))


def status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def reset_peak() -> int:
    """Reset the high-water mark; the resident kB it is measured from."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return status_kb("VmRSS")
    except OSError:
        return status_kb("VmHWM")


def peak_mb(rss0_kb: int) -> float:
    return (status_kb("VmHWM") - rss0_kb) / 1024


def train_pdm(actor_dir: Path, order: str, model_dir: Path, marker_noise_mm: float = 0.0) -> dict:
    """Train a PDM of ``order`` (and ``marker_noise_mm``) on the actor's training clips and
    save it into ``model_dir``; wall time and peak RSS of ``train`` (run it in a fresh
    process: :func:`run_worker`)."""
    from service.methods.pdm.model import PdmParams, train
    from service.samples.dataset import load_actor

    actor = load_actor(actor_dir)
    clips = training_clips(actor_dir, actor)
    params = PdmParams(order=order, marker_noise_mm=marker_noise_mm)
    rss0 = reset_peak()
    t0 = time.perf_counter()
    model = train(actor, clips, params,
                  lambda fr, stage: print(f"    [{order}] {fr:4.0%} {stage}", file=sys.stderr))
    res = {"order": order, "train_s": time.perf_counter() - t0, "peak_rss_mb": peak_mb(rss0),
           "frames": sum(c.frames for c in clips)}
    model.save(model_dir)
    return res


def run_worker(script: str, *args: str, cores: int | None = None) -> dict:
    """Run ``script`` (a report's own file) as a worker in a fresh process; its JSON result
    (last stdout line). ``cores``: pinned to that many CPUs, thread pools to match."""
    env, preexec = dict(os.environ), None
    if cores:
        cpus = sorted(os.sched_getaffinity(0))[:cores]
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
            env[var] = str(len(cpus))
        preexec = lambda: os.sched_setaffinity(0, cpus)       # noqa: E731
    proc = subprocess.run([sys.executable, script, *args], stdout=subprocess.PIPE, text=True,
                          check=False, env=env, preexec_fn=preexec)
    if proc.returncode != 0:
        sys.exit(f"worker {' '.join(args)} failed (exit {proc.returncode})")
    return json.loads(proc.stdout.strip().splitlines()[-1])


@dataclass
class DetailTexels:
    """Fine-map texels and the operators of the detail-height metric (module docstring).

    index (P,) covered texels (row-major) of the H×H map; interp (P,n) vertex → texel;
    corner (P,) first vertex of each texel's triangle; regions: actor region → (P,) bool
    (the texel's triangle's first vertex in the region); split: training's band split.
    """

    H: int
    index: np.ndarray
    interp: object
    corner: np.ndarray
    regions: dict
    split: object                      # service.methods.pdm.model.BandFilter

    @property
    def face(self) -> np.ndarray:
        return self.regions[FACE]

    @classmethod
    def build(cls, actor, H: int, sigma: float) -> "DetailTexels":
        from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
        from service.methods.pdm.model import BandFilter

        raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
        index = np.flatnonzero(raster.mask.ravel())
        interp = interpolation_matrix(raster, actor.faces, actor.n_vertices)[index].tocsr()
        corner = actor.faces[raster.triangle.ravel()[index], 0]
        regions = {k: np.asarray(v, bool)[corner] for k, v in actor.regions.items()}
        return cls(H, index, interp, corner, regions, BandFilter.build(H, index, sigma))

    def normals(self, medium: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Unit normals (k,P,3) float32 of the medium surfaces (k,n,3) at the texels."""
        from service.geometry.normals import vertex_normals

        out = np.empty((len(medium), len(self.index), 3), np.float32)
        for f, V in enumerate(medium):
            n = self.interp @ vertex_normals(V, faces, weighting="area")
            out[f] = n / np.linalg.norm(n, axis=1, keepdims=True)
        return out

    def highpass(self, values: np.ndarray) -> np.ndarray:
        """The fine band ``h − G_σ∗h`` (P,) of heights at the covered texels (training's split)."""
        return self.split.highpass(np.asarray(values, np.float64))

    def heights(self, V: np.ndarray, medium: np.ndarray, normals: np.ndarray,
                d: np.ndarray | None) -> np.ndarray:
        """Detail heights ``n·(P V − P V_medium) + d`` (P,) of one frame's mesh V and map d (P,)."""
        h = np.einsum("pd,pd->p", normals, self.interp @ (V - medium))
        return h if d is None else h + d

    def texels(self, image: np.ndarray) -> np.ndarray:
        """Covered texels (…,P) of maps (…,H,H)."""
        return image.reshape(*image.shape[:-2], -1)[..., self.index]

    def image(self, values: np.ndarray, only_face: bool = True) -> np.ndarray:
        """(P,) texel values → (H,H) map, NaN off the covered (face) texels."""
        img = np.full(self.H * self.H, np.nan)
        keep = self.face if only_face else np.ones(len(self.index), bool)
        img[self.index[keep]] = values[keep]
        return img.reshape(self.H, self.H)


def pdm_prediction(model, markers, tex: DetailTexels, clamp: bool = True):
    out = model.synthesize(markers, BASIC_OUTPUTS, clamp=clamp)
    return out["vertices"].astype(np.float64), tex.texels(out["displacement"]), out["clamped"]


def camera(actor, centre=None, zoom: float = 1.0, size: int = 480):
    """A front camera 600 mm away framing the narrow face (neutral pose), or ``zoom``× closer
    around ``centre`` (3,)."""
    from service.samples.render import face_cameras

    V = actor.vertices[np.asarray(actor.regions["narrow_face"])]
    lo, hi = V.min(axis=0), V.max(axis=0)
    if centre is None:
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    return face_cameras(np.asarray(centre, np.float64), distance=600.0, size=size, yaws_deg=(0.0,),
                        field_mm=1.2 * (hi[1] - lo[1]) / zoom)[0]


def plot_grazing(meshes: list[tuple[str, np.ndarray]], actor, zoom_centre: np.ndarray, caption: str,
                 path: Path) -> None:
    """(d) grey meshes (head pose removed) under grazing light: whole face, and a 3× close-up."""
    from PIL import Image, ImageDraw, ImageFont

    from service.samples.gallery import GRAZING_LIGHT
    from service.samples.render import shade, to_srgb8, write_png

    full, close = camera(actor), camera(actor, zoom_centre, zoom=3.0)
    grey = np.full((actor.n_vertices, 3), 0.6)
    font = ImageFont.load_default(size=15)
    rows = []
    for cam, suffix in ((full, caption), (close, "3x close-up")):
        tiles = []
        for label, V in meshes:
            img = Image.fromarray(to_srgb8(shade(cam, V, actor.faces, grey, light_dir=GRAZING_LIGHT, ambient=0.05)))
            ImageDraw.Draw(img).multiline_text((8, 6), f"{label}\n{suffix}", fill=(255, 255, 255), font=font)
            tiles.append(np.asarray(img))
        rows.append(np.concatenate(tiles, axis=1))
    write_png(path, np.concatenate(rows, axis=0))


def zoom_centre(tex: DetailTexels, hp_gt: np.ndarray, vertices: np.ndarray, sigma: float = 15.0) -> np.ndarray:
    """Where the ground truth's fine detail is strongest: the vertex (3,) under the texel of
    largest Gaussian-smoothed squared high-passed height in the narrow face."""
    from scipy.ndimage import gaussian_filter

    img = np.zeros(tex.H * tex.H)
    img[tex.index] = hp_gt ** 2
    energy = gaussian_filter(img.reshape(tex.H, tex.H), sigma).ravel()[tex.index]
    energy[~tex.regions["narrow_face"]] = -1.0
    return vertices[tex.corner[np.argmax(energy)]]


def git_state() -> str:
    """Commit of the checkout and the library files with uncommitted changes (others edit in parallel)."""
    def git(*a):
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()

    dirty = [line[3:] for line in git("status", "--porcelain", "--", "service").splitlines()]
    return f"commit {git('rev-parse', '--short', 'HEAD')}" + (
        f", uncommitted changes in {', '.join(dirty)}" if dirty else ", service/ clean")


# methods: (world vertices (k,n,3), fine maps at the texels (k,P) or None, clamped (k,) or None)
@dataclass
class Baselines:
    """What the baselines need from the training data and the biquadratic model."""

    model: object                      # the PdmModel whose deformation drives everything
    detailed: object                   # BaseSurface of the detailed neutral
    neutral_map: np.ndarray            # (P,) fine map of a neutral training frame
    train_aligned: np.ndarray          # (T,M,3) aligned training markers
    train_c: np.ndarray                # (T,n,3) float32 medium detail in base frames
    train_maps: np.ndarray             # (T,P) float32 relative fine maps

    @classmethod
    def build(cls, actor, clips, model, tex: DetailTexels) -> "Baselines":
        from service.methods.pdm.base_surface import BaseSurface

        base = model.base
        detailed = BaseSurface.from_smooth(actor.vertices, actor.faces, actor.uv, actor.uv_faces,
                                           base.handles, base.rest_markers)
        markers = np.concatenate([c.markers for c in clips])
        pose, u_H, _ = model.deformation(markers)
        V = np.concatenate([c.vertices for c in clips])
        c = np.empty(V.shape, np.float32)
        for t in range(len(V)):
            X = base.deform(u_H[t:t + 1])
            c[t] = np.einsum("fnij,fnj->fni", base.frames(X), pose[t:t + 1].remove(V[t:t + 1]) - X)[0]
        maps = np.concatenate([tex.texels(cl.displacement) for cl in clips]).astype(np.float32)
        neutral = next(cl for cl in clips if cl.name == NEUTRAL_CLIP)
        return cls(model, detailed, tex.texels(neutral.displacement[0]), pose.remove(markers), c, maps)

    def no_detail(self, markers):
        pose, u_H, _ = self.model.deformation(markers)
        return pose.restore(self.detailed.deform(u_H)), None, None

    def static_neutral_map(self, markers):
        V, _, _ = self.no_detail(markers)
        return V, np.broadcast_to(self.neutral_map, (len(markers), len(self.neutral_map))), None

    def nearest(self, markers) -> tuple[np.ndarray, np.ndarray, None, np.ndarray]:
        """Also returns the chosen training frame (k,) (global index)."""
        base = self.model.base
        pose, u_H, _ = self.model.deformation(markers)
        a = pose.remove(markers)
        d2 = np.nansum((a[:, None] - self.train_aligned[None]) ** 2, axis=(2, 3))    # (k,T)
        t = np.argmin(d2, axis=1)
        X = base.deform(u_H)
        V = pose.restore(X + np.einsum("fnji,fnj->fni", base.frames(X), self.train_c[t]))
        return V, self.train_maps[t], None, t


@dataclass
class Scores:
    """Pooled accumulators of one method on one performance, over one vertex and texel set."""

    vertices: np.ndarray                                   # (n,) bool scored vertices
    texels: np.ndarray                                     # (P,) bool scored texels
    vertex_errors: list = field(default_factory=list)     # (k_v,) per frame, mm
    sums: np.ndarray = field(default_factory=lambda: np.zeros(6))   # n, Σx, Σy, Σxx, Σyy, Σxy

    def add(self, err: np.ndarray, hp: np.ndarray, hp_gt: np.ndarray) -> None:
        """One frame: vertex errors (n,), predicted and ground-truth high-passed heights (P,)."""
        self.vertex_errors.append(err[self.vertices].astype(np.float32))
        x, y = hp[self.texels], hp_gt[self.texels]
        self.sums += [len(x), x.sum(), y.sum(), x @ x, y @ y, x @ y]

    def result(self) -> dict:
        e = np.concatenate(self.vertex_errors)
        n, sx, sy, sxx, syy, sxy = self.sums
        cov, vx, vy = sxy - sx * sy / n, sxx - sx * sx / n, syy - sy * sy / n
        return {"medium_mean_mm": float(e.mean()), "medium_p95_mm": float(np.percentile(e, 95)),
                "fine_r": float(cov / np.sqrt(vx * vy)) if vx > 0 else float("nan"),
                "fine_rms_mm": float(np.sqrt(max(sxx - 2 * sxy + syy, 0.0) / n))}


def evaluate_performance(gt: Heldout, methods: dict, tex: DetailTexels, actor, keep_frames) -> dict:
    """Scores of every method on one performance; the figure data of frames ``keep_frames``.

    methods: name → callable(markers) → (V, d, clamped[, extra]).
    Returns {"scores": region → name → metrics, "clamped": name → mean fraction,
    "signal_rms_mm": region → GT high-passed RMS, "figure": {...}, "extra": name → extra}.
    """
    from service.samples.dataset import vertex_detail_map

    normals = tex.normals(gt.medium, actor.faces)
    gt_hp = np.stack([tex.highpass(tex.texels(d)) for d in gt.displacement])       # (k,P)
    signal = {r: float(np.sqrt(np.mean(gt_hp[:, tex.regions[r]] ** 2))) for r in SCORED_REGIONS}
    keep = [int(np.flatnonzero(gt.frames == f)[0]) for f in keep_frames]
    figure = {"gt_hp": {gt.frames[i]: gt_hp[i] for i in keep}, "hp": {}, "vertex_error": {}}
    scores = {r: {} for r in SCORED_REGIONS}
    clamped_mean, extra = {}, {}

    # the metric's floor: the ground truth's mesh and relative map through the same pipeline
    relative = tex.texels(gt.displacement - vertex_detail_map(actor, gt.vertices, gt.medium, tex.H))
    methods = {GT_ROW: lambda m: (gt.vertices, relative, None), **methods}
    for name, method in methods.items():
        t0 = time.perf_counter()
        V, D, clamped, *more = method(gt.markers)
        if more:
            extra[name] = more[0]
        acc = {r: Scores(np.asarray(actor.regions[r]), tex.regions[r]) for r in SCORED_REGIONS}
        for f in range(len(gt.frames)):
            err = np.linalg.norm(V[f] - gt.vertices[f], axis=-1)
            hp = tex.highpass(tex.heights(V[f], gt.medium[f], normals[f], None if D is None else D[f]))
            for a in acc.values():
                a.add(err, hp, gt_hp[f])
            if f in keep:
                figure["hp"][(name, gt.frames[f])] = hp
                figure["vertex_error"][(name, gt.frames[f])] = err
        for r, a in acc.items():
            scores[r][name] = a.result()
        clamped_mean[name] = None if clamped is None else float(np.mean(clamped))
        print(f"    {gt.name} / {name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return {"scores": scores, "clamped": clamped_mean, "signal_rms_mm": signal, "figure": figure,
            "extra": extra}


def pdm_in_fresh_process(actor_dir: Path, order: str, model_dir: Path, marker_noise_mm: float = 0.0) -> dict:
    """:func:`train_pdm` run in a fresh process (its own peak memory); the training record."""
    return run_worker(__file__, "train-pdm", str(actor_dir), order, str(model_dir), str(marker_noise_mm))


if __name__ == "__main__":
    if len(sys.argv) in (5, 6) and sys.argv[1] == "train-pdm":
        print(json.dumps(train_pdm(Path(sys.argv[2]), sys.argv[3], Path(sys.argv[4]),
                                   float(sys.argv[5]) if len(sys.argv) == 6 else 0.0)))
    else:
        sys.exit("usage: harness.py train-pdm ACTOR_DIR ORDER MODEL_DIR (the reports' worker)")
