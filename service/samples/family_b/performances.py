"""Family b's performances: its own training set, timing, easing and head motion.

Written independently of family a's choices: 25 fps (family a 30), 26-frame training
clips with a cosine ease and a hold of 4 frames, ten training expressions at amplitudes
0.6–0.95 (family a: eight, mostly at 1.0, several of them blends), a larger head motion
about a lower pivot.

Held-out performances (names shared with family a, so every consumer finds them):

* ``heldout_in_range``: each training expression at 35–90 % of its peak, some one-sided,
  and light blends of two expressions that the database also shows; every weight within
  the training amplitudes;
* ``heldout_out_of_range``: training expressions 15–30 % beyond their peaks;
* ``heldout_combinations``: combinations no training clip shows (asymmetric smile with one
  brow raised, pucker with the jaw open, squint with sneer, …), each weight within the
  training amplitudes;
* ``heldout_amplified``: every training expression 25–40 % beyond its peak;
* ``database``: 600 frames of random blends of one or two training expressions and
  speech-like jaw motion, within the training amplitudes (bermano2014 §4.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

FPS = 25.0
HEAD_PIVOT_MM = np.array([0.0, -85.0, -25.0])
CLIP_FRAMES = 26
HOLD_FRAMES = 4

TRAINING: dict[str, dict[str, float]] = {
    "brow_raise": {"browInnerUp_L": 0.9, "browInnerUp_R": 0.9, "browOuterUp_L": 0.75,
                   "browOuterUp_R": 0.75},
    "brow_furrow": {"browDown_L": 0.85, "browDown_R": 0.85},
    "smile": {"mouthSmile_L": 0.9, "mouthSmile_R": 0.9, "cheekSquint_L": 0.45, "cheekSquint_R": 0.45},
    "squint": {"eyeSquint_L": 0.9, "eyeSquint_R": 0.9, "cheekSquint_L": 0.3, "cheekSquint_R": 0.3},
    "sneer": {"noseSneer_L": 0.85, "noseSneer_R": 0.85, "mouthUpperUp_L": 0.4, "mouthUpperUp_R": 0.4},
    "jaw_open": {"jawOpen": 0.6},
    "pucker": {"mouthPucker": 0.9, "mouthFunnel": 0.3},
    "frown": {"mouthFrown_L": 0.8, "mouthFrown_R": 0.8, "mouthShrugLower": 0.6},
    "blink": {"eyeBlink_L": 0.95, "eyeBlink_R": 0.95},
    "cheek_puff": {"cheekPuff_L": 0.7, "cheekPuff_R": 0.7},
}

COMBINATIONS: list[dict[str, float]] = [
    {},
    {"mouthSmile_R": 0.85, "cheekSquint_R": 0.4, "browInnerUp_L": 0.8, "browOuterUp_L": 0.7},
    {"mouthPucker": 0.85, "mouthFunnel": 0.25, "jawOpen": 0.5},
    {"eyeSquint_L": 0.85, "eyeSquint_R": 0.85, "noseSneer_L": 0.8, "noseSneer_R": 0.8,
     "mouthUpperUp_L": 0.35, "mouthUpperUp_R": 0.35},
    {},
    {"mouthSmile_L": 0.8, "mouthSmile_R": 0.8, "jawOpen": 0.55, "browInnerUp_L": 0.5,
     "browInnerUp_R": 0.5},
    {"browDown_L": 0.8, "browDown_R": 0.8, "mouthFrown_L": 0.7, "mouthFrown_R": 0.7},
    {"eyeBlink_R": 0.9, "mouthSmile_L": 0.7, "cheekPuff_R": 0.5},
    {},
]


@dataclass(frozen=True)
class Performance:
    """Blendshape weights (F,53) and head pose per frame: X_world = R (X − pivot) + pivot + t."""

    name: str
    kind: str
    weights: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    fps: float = FPS

    @property
    def frames(self) -> int:
        return len(self.weights)

    def pose(self, X: np.ndarray) -> np.ndarray:
        """Head-frame positions X (F,n,3) → world."""
        return np.einsum("fij,fnj->fni", self.rotation, X - HEAD_PIVOT_MM) + (HEAD_PIVOT_MM + self.translation)[:, None]


def cosine_ease(x: np.ndarray) -> np.ndarray:
    """(1 − cos πx)/2 on [0,1], clamped."""
    return 0.5 * (1 - np.cos(np.pi * np.clip(x, 0, 1)))


def vector(names: tuple[str, ...], shape: dict[str, float]) -> np.ndarray:
    w = np.zeros(len(names))
    for k, v in shape.items():
        w[names.index(k)] = v
    return w


def keyed(keys: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """Cosine-eased curve through keyframes (K,C) with spans (K−1,) frames: (Σspans+1, C)."""
    parts = [keys[:1]]
    for k, n in enumerate(spans):
        t = cosine_ease(np.arange(1, n + 1) / n)[:, None]
        parts.append(keys[k] + t * (keys[k + 1] - keys[k]))
    return np.concatenate(parts)


def head_motion(frames: int, rng: np.random.Generator, degrees: float = 4.5,
                mm: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (F,3,3) and translations (F,3): a slow random walk, low-passed (one-pole, 0.5 s)."""
    steps = rng.standard_normal((frames + 50, 6))
    alpha = 1 - np.exp(-1 / (0.5 * FPS))
    y = np.zeros_like(steps)
    for f in range(1, len(steps)):
        y[f] = y[f - 1] + alpha * (steps[f] - y[f - 1])
    y = y[50:]
    y /= np.maximum(np.abs(y).max(axis=0), 1e-9)
    return (Rotation.from_rotvec(np.deg2rad(degrees) * y[:, :3]).as_matrix(), mm * y[:, 3:])


def training_amplitudes(names: tuple[str, ...]) -> np.ndarray:
    """Largest weight (53,) each blendshape reaches in family b's training clips."""
    return np.max([vector(names, s) for s in TRAINING.values()], axis=0)


def training_clips(names: tuple[str, ...], seed: int) -> list[Performance]:
    rng = np.random.default_rng([seed, 0xB7])
    rise = (CLIP_FRAMES - 1 - HOLD_FRAMES) // 2
    out = []
    for name, shape in TRAINING.items():
        peak = vector(names, shape)
        w = keyed(np.stack([0 * peak, peak, peak, 0 * peak]),
                  np.array([rise, HOLD_FRAMES, CLIP_FRAMES - 1 - HOLD_FRAMES - rise]))
        R, t = head_motion(len(w), rng, 2.5, 2.5)
        out.append(Performance(f"train_{name}", "training", w, R, t))
    return out


def _performance(names, keys, name, kind, rng, span=(11, 17)) -> Performance:
    K = np.stack([vector(names, k) for k in keys])
    w = keyed(K, rng.integers(span[0], span[1] + 1, size=len(K) - 1))
    R, t = head_motion(len(w), rng)
    return Performance(name, kind, w, R, t)


def _scaled_training(rng, lo, hi, one_sided: float = 0.0) -> list[dict[str, float]]:
    keys = [{}]
    for shape in TRAINING.values():
        f = rng.uniform(lo, hi)
        key = {k: v * f for k, v in shape.items()}
        if rng.uniform() < one_sided:
            side = rng.choice(["_L", "_R"])
            key = {k: v for k, v in key.items() if not k.endswith("_R" if side == "_L" else "_L")}
        keys.append(key)
    return keys + [{}]


def heldout_in_range(names, seed) -> Performance:
    rng = np.random.default_rng([seed, 0xB8])
    keys = _scaled_training(rng, 0.35, 0.9, one_sided=0.4)
    keys.insert(6, {k: 0.5 * v for s in ("smile", "squint") for k, v in TRAINING[s].items()})
    return _performance(names, keys, "heldout_in_range", "heldout_in_range", rng, span=(9, 14))


def heldout_out_of_range(names, seed) -> Performance:
    rng = np.random.default_rng([seed, 0xB9])
    keys = _scaled_training(rng, 1.15, 1.30)[:7] + [{}]
    return _performance(names, keys, "heldout_out_of_range", "heldout_out_of_range", rng)


def heldout_combinations(names, seed) -> Performance:
    rng = np.random.default_rng([seed, 0xBA])
    return _performance(names, COMBINATIONS, "heldout_combinations", "heldout_combinations", rng)


def heldout_amplified(names, seed) -> Performance:
    rng = np.random.default_rng([seed, 0xBB])
    return _performance(names, _scaled_training(rng, 1.25, 1.40), "heldout_amplified",
                        "heldout_out_of_range", rng, span=(8, 12))


def database(names, seed, frames: int = 600) -> Performance:
    rng = np.random.default_rng([seed, 0xBC])
    shapes = [vector(names, s) for s in TRAINING.values()]
    keys, spans = [np.zeros(len(names))], []
    while sum(spans) < frames - 1:
        pick = rng.choice(len(shapes), size=rng.integers(1, 3), replace=False)
        keys.append(np.max([shapes[i] * rng.uniform(0.25, 1.0) for i in pick], axis=0))
        spans.append(int(rng.integers(10, 22)))
    spans[-1] -= sum(spans) - (frames - 1)
    W = keyed(np.stack(keys), np.array(spans))
    j = names.index("jawOpen")
    talk = 0.15 * (1 - np.cos(2 * np.pi * np.cumsum(rng.uniform(1.5, 3.5, frames)) / FPS))
    W[:, j] = np.maximum(W[:, j], talk)
    W = np.minimum(W, training_amplitudes(names))
    R, t = head_motion(frames, rng)
    return Performance("database", "database", W, R, t)


def all_performances(names: tuple[str, ...], seed: int) -> list[Performance]:
    """Training clips, the four held-out performances and the database, in build order."""
    return training_clips(names, seed) + [heldout_in_range(names, seed),
                                          heldout_out_of_range(names, seed),
                                          heldout_combinations(names, seed),
                                          heldout_amplified(names, seed),
                                          database(names, seed)]
