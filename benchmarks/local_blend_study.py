"""What WPSD + marker regression misses on held-out poses (issue 17, session 19), and whether a
per-patch blend of the training frames' detail carries it.

Usage: ``python benchmarks/local_blend_study.py FAMILY=ACTOR_DIR ... [--frames 6]
[--ranges ...] [--conditions clean ...]``. Uses the cached 'WPSD + marker regression (s=3, λ=0.1)'
model of ``generalization_report.py`` (trains it if missing). Writes
``benchmarks/out/local_blend_study/<actor>.json`` and a markdown table on stdout.

Rows (detail rel err, the report's metric: high-passed ``n·(V − V_medium) + d`` at the face
texels, RMS error / the truth's RMS), for the model's mesh V and map d and the truth's
(V_gt, d_gt relative to V_gt):

* ``full`` (V, d); ``mesh`` (V, d_gt): what the mesh costs; ``map`` (V_gt, d): what the map costs;
* ``S:RIDGE:MU: map`` / ``mesh`` / ``both``: the model with its map, its RBF corrections or
  both replaced by the per-patch blend of the training frames (:class:`PatchBlend`), weights
  from each patch's markers;
* decomposition of the mesh: ``shell leak`` / ``shell + regression leak`` (hp of the shell's,
  the shell plus the regression's deviation from the truth's medium surface, over the truth's
  detail RMS); oracles (weights fitted to the truth, per marker patch of radius s): the
  training frames' medium corrections (``oracle medium blend``, truth's detail on top), their
  detail corrections on the truth's medium surface (``oracle detail blend``), the RBF targets
  (``oracle patch blend``), the corrections before the regression (``oracle full-correction``);
* ``--eval JSON``: the model with evaluation-only parameter changes (e.g. the marker posterior).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import harness as pr  # noqa: E402
from service.geometry.marker_regression import marker_weights  # noqa: E402

OUT = pr.OUT / "local_blend_study"
ORACLE_RADII = [1.5]
MODEL_DIRS: dict = {}    # actor directory name → model directory (--model)
VARIANTS: list = []      # evaluation-only parameter changes (JSON), one row each
NAME = "WPSD + marker regression (s=3, λ=0.1)"


# ---------------------------------------------------------------------------------------
# the candidate: a per-patch blend of the training frames, weights regressed from the patch's
# markers. Every marker m is the centre of a patch with Gaussian weights over the markers
# g_m,k = exp(−‖r_m − r_k‖²/s²) (marker_regression.marker_weights); the frame weights of patch m
# are the non-negative fit of its markers' displacements by the training frames' (relative to
# the rest frame 0), with a ridge λ̂ = λ tr(A_m)/T and a locality term μ Σ_t d²_m,t w_t² (d²_m,t
# the patch's distance from the query to frame t: prefers the nearest frames), solved by FISTA:
#     w_m = argmin_{w ≥ 0} Σ_k g_m,k ‖u_k − Σ_t w_t u_t,k‖² + λ̂ ‖w‖² + μ Σ_t d²_m,t w_t²;
# a vertex blends y_0 + Σ_t ω_t (y_t − y_0), ω = Σ_m ĝ_v,m w_m (ĝ its row-normalized patch
# weights). Measured here: no gain over WPSD's RBFs (README / the session-19 report).

#: patch kernel entries g below this are dropped
CUTOFF = 1e-3
#: projected-gradient iterations of the per-patch non-negative fit
ITERATIONS = 200


@dataclass(frozen=True)
class PatchBlend:
    """The per-patch frame-weight regression (module docstring).

    U (T,M,3) training handle displacements relative to the rest frame, rest (M,3) the rest
    frame's displacements, G (M,M) CSR patch kernel g, A (M,T,T) the patches' Gram matrices
    with the ridge on the diagonal, step (M,) 1 / largest eigenvalue of A_m, vertex_patch (n,M)
    CSR row-normalized ĝ, first the rest frame's index.
    """

    U: np.ndarray
    norms: np.ndarray
    rest: np.ndarray
    G: sp.csr_matrix
    A: np.ndarray
    step: np.ndarray
    vertex_patch: sp.csr_matrix
    first: int

    @classmethod
    def build(cls, u: np.ndarray, first: int, vertices: np.ndarray, marker_rest: np.ndarray,
              radius: float, ridge: float) -> "PatchBlend":
        """From training handle displacements u (T,M,3), the rest frame's index ``first``, rest
        vertices (n,3) and markers (M,3), mm; ``radius`` s (mm), ``ridge`` λ (relative)."""
        u = np.asarray(u, np.float64)
        T, M, _ = u.shape
        U = u - u[first]
        G = marker_weights(marker_rest, marker_rest, radius, CUTOFF)                # (M,M)
        K = np.einsum("tmc,smc->mts", U, U).reshape(M, T * T)                     # U_k U_kᵀ
        A = np.asarray(G @ K).reshape(M, T, T)
        lam = ridge * np.maximum(np.einsum("mtt->m", A) / T, 1e-30)
        A[:, np.arange(T), np.arange(T)] += lam[:, None]
        step = 1.0 / np.linalg.eigvalsh(A)[:, -1]
        Vp = marker_weights(np.asarray(vertices, np.float64), marker_rest, radius, CUTOFF)
        Vp = sp.diags(1.0 / np.maximum(np.asarray(Vp.sum(axis=1)).ravel(), 1e-300)) @ Vp
        return cls(U, np.einsum("tmc,tmc->mt", U, U), u[first], G.tocsr(), A, step, Vp.tocsr(), int(first))

    @property
    def n_frames(self) -> int:
        return self.U.shape[0]

    def patch_weights(self, u: np.ndarray, locality: float = 0.0, iterations: int = ITERATIONS) -> np.ndarray:
        """Non-negative frame weights w (F,M,T) of every patch for handle displacements u (F,M,3);
        ``locality`` μ adds μ Σ_t d²_m,t w_t² (d²_m,t the patch's distance Σ_k g_m,k ‖u_k − u_t,k‖²
        of the query to frame t), preferring the frames nearest the query."""
        d = np.asarray(u, np.float64) - self.rest                                  # (F,M,3)
        Z = np.einsum("tmc,fmc->fmt", self.U, d)                                   # U_kᵀ u_k
        b = np.stack([self.G @ z for z in Z])                                      # (F,M,T)
        A = self.A
        if locality > 0:
            q2 = np.einsum("fmc,fmc->fm", d, d)
            D2 = np.stack([self.G @ (q[:, None] - 2.0 * z + self.norms) for q, z in zip(q2, Z)])
            pen = locality * np.maximum(D2, 0.0)                                   # (F,M,T)
            step = 1.0 / (1.0 / self.step[None, :, None] + pen.max(axis=2, keepdims=True))
        else:
            pen = 0.0
            step = self.step[None, :, None]
        w = np.zeros_like(b)
        y, t = w.copy(), 1.0
        for _ in range(iterations):                                                # FISTA
            grad = np.einsum("mts,fms->fmt", A, y) + pen * y - b
            w_next = np.maximum(y - step * grad, 0.0)
            t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            y = w_next + ((t - 1.0) / t_next) * (w_next - w)
            w, t = w_next, t_next
        return w

    def frame_weights(self, u: np.ndarray, rows: sp.spmatrix | None = None) -> np.ndarray:
        """Affine blend weights ω̃ (F,n,T) of the vertices (or of ``rows`` @ vertices, e.g. texels
        (Pt,n)) for handle displacements u (F,M,3): Σ_m ĝ_v,m w_m with the rest frame's
        weight raised by 1 − Σ_t ω_t, so that ``ω̃ @ y`` is the module docstring's y(u)."""
        w = self.patch_weights(u)
        R = self.vertex_patch if rows is None else (rows @ self.vertex_patch).tocsr()
        out = np.stack([R @ wf for wf in w])                                       # (F,n,T)
        out[:, :, self.first] += 1.0 - out.sum(axis=2)
        return out


class Study(pr.DetailMetric):
    """One actor: the cached WPSD + regression model, its training data on the model's shell."""

    def __init__(self, actor_dir: Path, params=None):
        from service.methods.pdm.model import mean_texel_size
        from service.methods.pdm.params import PdmParams
        from service.methods.pose_space import PoseSpaceModel, WpsdParams
        from service.samples.dataset import load_actor

        self.dir = actor_dir
        self.actor = actor = load_actor(actor_dir)
        params = params or WpsdParams(marker_regression=3.0, marker_regression_ridge=0.1)
        path = MODEL_DIRS.get(actor_dir.name) or pr.pose_space_model(actor_dir, params, False)[0]
        self.model = PoseSpaceModel.load(path)
        clips = pr.training_clips(actor_dir, actor)
        H = clips[0].displacement.shape[1]
        # the report's band split: the biquadratic PDM's σ at the actor's map resolution
        bq = pr.generalization_pdm_models(actor_dir, False, 0.0, None, ["biquadratic"])["biquadratic"]
        self.tex = tex = pr.DetailTexels.build(actor, H, bq.metrics["highpass_sigma_texels"] * H / bq.data.fine.resolution)
        del bq
        ev = self.model.evaluator
        self.base = base = ev.base
        markers = np.concatenate([c.markers for c in clips])
        pose, u_H = ev.deformation(markers)
        self.u_H = u_H
        X = base.deform(u_H)
        V = pose.remove(np.concatenate([c.vertices for c in clips]))
        lin = ev.regression_offsets(u_H)
        Fr = base.frames(X)
        self.C = np.einsum("fnij,fnj->fni", Fr, V - X - lin).astype(np.float32)   # RBF targets
        self.C_full = np.einsum("fnij,fnj->fni", Fr, V - X).astype(np.float32)    # before the regression
        med = []
        for c in clips:
            with np.load(actor_dir / "performances" / f"{c.name}.npz") as z:
                med.append(z["vertices_medium"].astype(np.float64))
        Ma = pose.remove(np.concatenate(med))
        self.C_med = np.einsum("fnij,fnj->fni", Fr, Ma - X - lin).astype(np.float32)   # medium part of C
        self.C_det = np.einsum("fnij,fnj->fni", Fr, V - Ma).astype(np.float32)         # detail part
        del Fr
        self.maps = np.concatenate([tex.texels(c.displacement) for c in clips]).astype(np.float32)
        self.F = ev.features(u_H)
        self.first = int(np.argmin(np.linalg.norm(self.F, axis=1)))
        import dataclasses

        from service.methods.pose_space.model import PoseSpaceEvaluator
        self.variants = {}
        for v in VARIANTS:
            d2 = dataclasses.replace(self.model.data, params=self.model.params.model_copy(update=json.loads(v)))
            self.variants[v] = PoseSpaceModel(d2, PoseSpaceEvaluator(d2, base))
        del clips

    def heldout(self, perf: str, suffix: str, frames: int | None):
        """The report's held-out frames of a performance (``suffix``: its marker variant)."""
        gt = pr.heldout_frames(self.dir, perf, frames)
        if suffix:
            gt.markers = pr.variant_markers(self.dir, perf + suffix, gt.frames)
        return self.prepared(gt)


def run(st: Study, gt, blenders: dict) -> dict:
    ev, base = st.model.evaluator, st.base
    out = st.model.synthesize(gt.markers, ("mesh", "displacement"))
    V, D = out["vertices"].astype(np.float64), st.tex.texels(out["displacement"])
    rows = {"full": st.score(gt, st.hp(gt, V, D), V),
            "mesh": st.score(gt, st.hp(gt, V, gt.rel_map)),
            "map": st.score(gt, st.hp(gt, gt.vertices, D))}
    for key, m in st.variants.items():
        out = m.synthesize(gt.markers, ("mesh", "displacement"))
        Vn, Dn = out["vertices"].astype(np.float64), st.tex.texels(out["displacement"])
        rows[f"{key}: full"] = st.score(gt, st.hp(gt, Vn, Dn), Vn)
        rows[f"{key}: mesh"] = st.score(gt, st.hp(gt, Vn, gt.rel_map), Vn)
    pose, u_H = ev.deformation(gt.markers)
    X = base.deform(u_H)
    Fr = base.frames(X)
    lin = ev.regression_offsets(u_H)
    # oracle: per patch the least-squares blend of the training corrections closest to the truth's
    Va = pose.remove(gt.vertices)
    Cstar = np.einsum("fnij,fnj->fni", Fr, Va - X - lin)
    Ma = pose.remove(gt.medium)
    leak = st.hp(gt, pose.restore(X), np.zeros_like(D))
    face = st.tex.face
    ratio = lambda h: float(np.sqrt(np.sum(h[:, face] ** 2) / np.sum(gt.hp[:, face] ** 2)))   # noqa: E731
    rows["shell leak"] = {"rel": ratio(leak), "r": 0.0}
    rows["shell + regression leak"] = {"rel": ratio(st.hp(gt, pose.restore(X + lin), np.zeros_like(D))), "r": 0.0}
    rows["truth medium + model map"] = st.score(gt, st.hp(gt, gt.medium, D))
    for rad in ORACLE_RADII:
        Cm = np.einsum("fnij,fnj->fni", Fr, Ma - X - lin)
        Vo = pose.restore(X + lin + np.einsum("fnji,fnj->fni", Fr, oracle(st, Cm, rad, train=st.C_med)) + (Va - Ma))
        rows[f"oracle medium blend s={rad:g} + truth detail"] = st.score(gt, st.hp(gt, Vo, gt.rel_map), Vo)
        Cd = np.einsum("fnij,fnj->fni", Fr, Va - Ma)
        Vo = pose.restore(Ma + np.einsum("fnji,fnj->fni", Fr, oracle(st, Cd, rad, train=st.C_det)))
        rows[f"truth medium + oracle detail blend s={rad:g}"] = st.score(gt, st.hp(gt, Vo, gt.rel_map), Vo)
        Vo = pose.restore(X + lin + np.einsum("fnji,fnj->fni", Fr, oracle(st, Cstar, rad)))
        rows[f"oracle patch blend s={rad:g}: mesh"] = st.score(gt, st.hp(gt, Vo, D), Vo)
        Cfull = np.einsum("fnij,fnj->fni", Fr, Va - X)
        Vo = pose.restore(X + np.einsum("fnji,fnj->fni", Fr, oracle(st, Cfull, rad, train=st.C_full)))
        rows[f"oracle full-correction blend s={rad:g}: mesh"] = st.score(gt, st.hp(gt, Vo, D), Vo)
    rows["truth residual (check)"] = st.score(gt, st.hp(gt, pose.restore(X + lin + np.einsum("fnji,fnj->fni", Fr, Cstar)), D))
    for bname, blend in blenders.items():
        c = np.empty(X.shape)
        Db = np.empty_like(D)
        for k in range(len(X)):                   # (n,T) vertex and (Pt,T) texel weights
            Wv, Wt = blend(u_H[k:k + 1])
            c[k] = np.einsum("nt,tnc->nc", Wv, st.C)
            Db[k] = np.einsum("pt,tp->p", Wt, st.maps)
        Vb = pose.restore(X + lin + np.einsum("fnji,fnj->fni", Fr, c))
        rows[f"{bname}: map"] = st.score(gt, st.hp(gt, V, Db), V)
        rows[f"{bname}: mesh"] = st.score(gt, st.hp(gt, Vb, D), Vb)
        rows[f"{bname}: both"] = st.score(gt, st.hp(gt, Vb, Db), Vb)
    return rows


def oracle(st: Study, Cstar: np.ndarray, radius: float = 1.5, ridge: float = 1e-6, train=None) -> np.ndarray:
    """Per marker patch (Gaussian PoU, s = ``radius`` spacings) the ridge least-squares blend of
    the training corrections st.C (T,n,3) fitted to the truth's Cstar (k,n,3); blended (k,n,3)."""
    from service.geometry.marker_regression import marker_spacing, marker_weights

    rest = st.model.data.rest_markers
    g = marker_weights(st.actor.vertices, rest, radius * marker_spacing(rest), 1e-3).tocsc()   # (n,M)
    rs = np.asarray(g.sum(axis=1)).ravel()
    out = np.zeros(Cstar.shape)
    C = st.C if train is None else train
    T = len(C)
    for m in range(g.shape[1]):
        vs = g.indices[g.indptr[m]:g.indptr[m + 1]]
        wv = np.sqrt(g.data[g.indptr[m]:g.indptr[m + 1]])[:, None]
        Cm = (C[:, vs].astype(np.float64) * wv).reshape(T, -1)
        A = Cm @ Cm.T
        A[np.diag_indices(T)] += ridge * np.trace(A) / T + 1e-300
        b = (Cstar[:, vs] * wv).reshape(len(Cstar), -1) @ Cm.T                  # (k,T)
        w = np.linalg.solve(A, b.T).T
        share = (g.data[g.indptr[m]:g.indptr[m + 1]] / rs[vs])[:, None]
        out[:, vs] += np.einsum("kt,tnc->knc", w, C[:, vs]) * share
    return out


def blender(st: Study, radius: float, ridge: float, locality: float = 0.0):
    """u_H (1,M,3) → vertex (n,T) and texel (Pt,T) weights of a PatchBlend with s = ``radius``
    median marker spacings and ridge λ."""
    from service.geometry.marker_regression import marker_spacing
    rest = st.model.data.rest_markers
    pb = PatchBlend.build(st.u_H, st.first, st.actor.vertices, rest, radius * marker_spacing(rest), ridge)
    interp = st.tex.interp

    def weights(u):
        w = pb.patch_weights(u, locality)[0]                                    # (M,T)
        Wv = pb.vertex_patch @ w
        Wv[:, pb.first] += 1.0 - Wv.sum(axis=1)
        return Wv, interp @ Wv
    return weights


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("actors", nargs="+", metavar="FAMILY=DIR")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--ranges", nargs="+", default=list(pr.HELDOUT_RANGES))
    ap.add_argument("--conditions", nargs="+", default=["clean"])
    ap.add_argument("--blend", nargs="*", default=["1.5:0.01"], metavar="S:RIDGE[:MU]",
                    help="PatchBlend radius (median marker spacings), ridge and locality")
    ap.add_argument("--oracle", nargs="*", type=float, default=[1.5])
    ap.add_argument("--model", nargs="*", default=[], metavar="ACTOR_DIR=MODEL_DIR",
                    help="a model directory to use instead of the cached default one")
    ap.add_argument("--eval", nargs="*", default=[], metavar="JSON",
                    help='evaluation-only parameter changes, e.g. \'{"marker_prior": "none"}\'')
    args = ap.parse_args()
    ORACLE_RADII[:] = args.oracle
    VARIANTS[:] = args.eval
    for item in args.model:
        k, _, v = item.partition("=")
        MODEL_DIRS[Path(k).name] = Path(v)
    OUT.mkdir(parents=True, exist_ok=True)
    for item in args.actors:
        fam, _, d = item.partition("=")
        t0 = time.perf_counter()
        st = Study(Path(d).resolve())
        print(f"[{fam}] loaded in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        blenders = {k: blender(st, *map(float, k.split(":"))) for k in args.blend}
        res = {}
        for rname in args.ranges:
            for cname in args.conditions:
                gt = st.heldout(pr.HELDOUT_RANGES[rname], pr.MARKER_CONDITIONS[cname], args.frames)
                rows = run(st, gt, blenders)
                res[f"{rname} / {cname}"] = rows
                for k, r in rows.items():
                    extra = f" | {r['mean']:.3f} | {r['max']:.2f}" if "mean" in r else " | |"
                    print(f"| {fam} | {rname} | {cname} | {k} | {r['rel']:.3f} | {r['r']:.2f}{extra} |", flush=True)
        (OUT / f"{Path(d).name}.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
