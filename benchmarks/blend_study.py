"""Where marker-driven detail loses accuracy (issue 17, session 17): the detail error of the
nearest training frame and of WPSD split into the part carried by the mesh and the part
carried by the fine maps.

Usage: ``python benchmarks/blend_study.py ACTOR_DIR [--frames N] [--conditions clean,noisy]
[--regression S]`` (``--regression``: instead of the decomposition, the nearest frame, WPSD and
WPSD with ``marker_regression = S`` on the full metric, with mean / max vertex error).
Output: ``benchmarks/out/blend_study/<actor>.json`` and a markdown table on stdout.

Metric (``harness.DetailTexels``): the high-passed normal-direction detail height
``hp(n·(V − V_medium) + d)`` at the face texels, over the truth's smooth surface V_medium,
rel err = RMS error / RMS of the truth's ``hp`` (pooled over frames), r = Pearson.

Decomposition of a method's (mesh V, map d), truth (V_gt, d_gt relative to V_gt):

* ``full``     (V, d)            — the method as scored;
* ``mesh``     (V, d_gt)         — the method's mesh with the truth's map: what the mesh costs;
* ``map``      (V_gt, d)         — the truth's mesh with the method's map: what the map costs;
* nearest frame only: ``medium`` its correction's medium part ``c_med = Frame(X_t)(M_t − X_t)``
  (M_t the training frame's smooth surface) re-posed on the held-out shell, with the truth's
  detail on top (``X + Frame(X)ᵀ c_med + (V_gt − M)``, d_gt): the error of the medium band
  as carried between poses; ``detail`` its detail part ``c_det = Frame(X_t)(V_t − M_t)``
  re-posed onto the truth's smooth surface (``M + Frame(X)ᵀ c_det``, d_t);
* ``shell leak``: hp(n·(X − M)) of the held-out thin shell X (RMS over the truth's detail RMS):
  what the corrections must cancel at the metric's scale.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402

import harness as pr  # noqa: E402

OUT = pr.OUT / "blend_study"
RANGES = pr.HELDOUT_RANGES
CONDITIONS = pr.MARKER_CONDITIONS


class Study(pr.DetailMetric):
    """One actor's training data on the WPSD model's shell, and the metric."""

    def __init__(self, actor_dir: Path, retrain: bool = False):
        from service.methods.pdm.model import mean_texel_size
        from service.methods.pdm.params import PdmParams
        from service.methods.pose_space import PoseSpaceModel, WpsdParams, train
        from service.methods.pose_space.corrections import corrections
        from service.samples.dataset import load_actor

        self.dir = actor_dir
        self.actor = actor = load_actor(actor_dir)
        clips = pr.training_clips(actor_dir, actor)
        path = OUT / "models" / actor_dir.name / "WPSD"
        if not retrain and (path / "manifest.json").is_file():
            self.model = PoseSpaceModel.load(path)
        else:
            t0 = time.process_time()
            self.model = train(actor, clips, WpsdParams(marker_regression=None))
            print(f"[{actor_dir.name}] WPSD trained in {time.process_time() - t0:.0f} s CPU", file=sys.stderr)
            self.model.save(path)
        H = clips[0].displacement.shape[1]
        sigma = PdmParams().fine_highpass_mm / mean_texel_size(actor, H)
        self.tex = tex = pr.DetailTexels.build(actor, H, sigma)
        ev = self.model.evaluator
        self.base = base = ev.base
        cache = OUT / f"{actor_dir.name}_train.npz"
        if cache.is_file() and not retrain:
            with np.load(cache) as z:
                for k in z.files:
                    setattr(self, k, z[k])
            self.C_det = self.C - self.C_med
            return
        markers = np.concatenate([c.markers for c in clips])
        pose, u_H = ev.deformation(markers)
        self.u_H = u_H                                                         # (T,M,3)
        self.train_aligned = pose.remove(markers)
        self.F = ev.features(u_H)                                              # (T,E)
        V = np.concatenate([c.vertices for c in clips])
        med = []
        for c in clips:
            with np.load(actor_dir / "performances" / f"{c.name}.npz") as z:
                med.append(z["vertices_medium"].astype(np.float64))
        M = np.concatenate(med)
        self.C = corrections(base, u_H, pose.remove(V))                       # (T,n,3) c
        self.C_med = corrections(base, u_H, pose.remove(M))                   # c_med
        self.C_det = self.C - self.C_med                                      # c_det
        self.maps = np.concatenate([tex.texels(c.displacement) for c in clips]).astype(np.float32)
        self.clip_of = np.concatenate([np.full(c.frames, i) for i, c in enumerate(clips)])
        # the training frames' own detail as the metric sees it: hp(n·(V − M)) + relative map
        normals = tex.normals(M, actor.faces)
        self.train_hp = np.stack([tex.highpass(tex.heights(V[t], M[t], normals[t], self.maps[t]))
                                  for t in range(len(V))]).astype(np.float32)   # (T,P)
        np.savez(cache, u_H=u_H, train_aligned=self.train_aligned, F=self.F, C=self.C, C_med=self.C_med,
                 maps=self.maps, clip_of=self.clip_of, train_hp=self.train_hp)
        del clips

    # ---- held-out frames
    def heldout(self, perf: str, suffix: str, frames: int | None):
        gt = pr.load_heldout(self.dir, perf, frames)
        if suffix:
            with np.load(self.dir / "performances" / f"{perf}{suffix}.npz") as z:
                gt.markers = z["markers"][gt.frames].astype(np.float64)
        return self.prepared(gt)

    def shell(self, markers: np.ndarray):
        """(pose, u_H, aligned shell X (k,n,3), frames (k,n,3,3)) of held-out markers."""
        pose, u_H = self.model.evaluator.deformation(markers)
        X = self.base.deform(u_H)
        return pose, u_H, X, self.base.frames(X)

    def nearest(self, markers: np.ndarray) -> np.ndarray:
        """Training frame (k,) of nearest aligned markers (harness.Baselines.nearest's rule)."""
        pose, _ = self.model.evaluator.deformation(markers)
        a = pose.remove(markers)
        d2 = np.nansum((a[:, None] - self.train_aligned[None]) ** 2, axis=(2, 3))
        return np.argmin(d2, axis=1)


def to_world(frames: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Offsets c (k,n,3) in tangent frames (k,n,3,3) (rows T, B, N) as world vectors."""
    return np.einsum("fnji,fnj->fni", frames, c)


def decompose(st: Study, gt) -> dict:
    """The rows of the module docstring for the nearest frame and WPSD on one performance."""
    pose, u_H, X, Fr = st.shell(gt.markers)
    Ma = pose.remove(gt.medium)
    Va = pose.remove(gt.vertices)
    rows = {}
    truth_det = Va - Ma
    # shell leak as a ratio: hp(n·(X − M)) against the truth's detail
    leak = st.hp(gt, pose.restore(X), np.zeros_like(gt.rel_map))
    face = st.tex.face
    rows["shell leak"] = {"rel": float(np.sqrt(np.sum(leak[:, face] ** 2) / np.sum(gt.hp[:, face] ** 2))), "r": None}
    t = st.nearest(gt.markers)
    Vn = pose.restore(X + to_world(Fr, st.C[t]))
    Dn = st.maps[t]
    rows["nearest: full"] = st.score(gt, st.hp(gt, Vn, Dn))
    rows["nearest: mesh"] = st.score(gt, st.hp(gt, Vn, gt.rel_map))
    rows["nearest: map"] = st.score(gt, st.hp(gt, gt.vertices, Dn))
    rows["nearest: medium"] = st.score(gt, st.hp(gt, pose.restore(X + to_world(Fr, st.C_med[t]) + truth_det), gt.rel_map))
    rows["nearest: detail"] = st.score(gt, st.hp(gt, pose.restore(Ma + to_world(Fr, st.C_det[t])), Dn))
    rows["nearest (own maps, direct)"] = st.score(gt, st.train_hp[t])
    out = st.model.synthesize(gt.markers, ("mesh", "displacement"))
    Vw, Dw = out["vertices"].astype(np.float64), st.tex.texels(out["displacement"])
    rows["WPSD: full"] = st.score(gt, st.hp(gt, Vw, Dw))
    rows["WPSD: mesh"] = st.score(gt, st.hp(gt, Vw, gt.rel_map))
    rows["WPSD: map"] = st.score(gt, st.hp(gt, gt.vertices, Dw))
    return rows


def regression_model(st: Study, s: float):
    """WPSD with ``marker_regression = s`` (service path), trained once and cached."""
    from service.methods.pose_space import PoseSpaceModel, WpsdParams, train

    path = OUT / "models" / st.dir.name / f"WPSD_reg{s}"
    if (path / "manifest.json").is_file():
        return PoseSpaceModel.load(path)
    t0 = time.process_time()
    m = train(st.actor, pr.training_clips(st.dir, st.actor), WpsdParams(marker_regression=s))
    print(f"[{st.dir.name}] WPSD + regression trained in {time.process_time() - t0:.0f} s CPU", file=sys.stderr)
    m.save(path)
    return m


def compare(st: Study, gt, model, s: float) -> dict:
    """Full-metric rows (rel, r, mean / max face vertex error mm) of the nearest frame, WPSD and
    WPSD + marker regression on one performance."""
    pose, _, X, Fr = st.shell(gt.markers)
    t = st.nearest(gt.markers)
    rows = {"nearest training frame": (pose.restore(X + to_world(Fr, st.C[t])), st.maps[t])}
    for name, m in (("WPSD", st.model), (f"WPSD + marker regression (s={s})", model)):
        o = m.synthesize(gt.markers)
        rows[name] = (o["vertices"].astype(np.float64), st.tex.texels(o["displacement"]))
    face = st.actor.regions[pr.FACE]
    res = {}
    for k, (V, D) in rows.items():
        e = np.linalg.norm(V - gt.vertices, axis=-1)[:, face]
        res[k] = {**st.score(gt, st.hp(gt, V, D)), "mean_mm": float(e.mean()), "max_mm": float(e.max())}
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("actors", nargs="+", type=Path)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--conditions", default="clean")
    ap.add_argument("--retrain", action="store_true")
    ap.add_argument("--regression", type=float, default=None,
                    help="compare nearest / WPSD / WPSD + marker regression with this s instead")
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    for d in a.actors:
        st = Study(d, a.retrain)
        if a.regression is not None:
            model, res = regression_model(st, a.regression), {}
            for rname, perf in RANGES.items():
                for cond in a.conditions.split(","):
                    res[f"{rname} / {cond}"] = rows = compare(st, st.heldout(perf, CONDITIONS[cond], a.frames),
                                                              model, a.regression)
                    for k, v in rows.items():
                        print(f"| {d.name} | {rname} | {cond} | {k} | {v['rel']:.3f} | {v['r']:.3f} | "
                              f"{v['mean_mm']:.3f} | {v['max_mm']:.2f} |", flush=True)
            (OUT / f"{d.name}_regression{a.regression}.json").write_text(json.dumps(res, indent=1))
            continue
        res = {}
        for rname, perf in RANGES.items():
            for cond in a.conditions.split(","):
                gt = st.heldout(perf, CONDITIONS[cond], a.frames)
                res[f"{rname} / {cond}"] = decompose(st, gt)
                print(f"## {d.name} {rname} / {cond}", flush=True)
                for k, v in res[f"{rname} / {cond}"].items():
                    print(f"| {k} | {v['rel']:.3f} | {'' if v['r'] is None else round(v['r'], 3)} |", flush=True)
        (OUT / f"{d.name}.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
