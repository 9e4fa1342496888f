"""Expression performances of the sample actor: blendshape-weight curves plus head motion.

* training clips in the manner of ma2008 §3: neutral → one strong expression → neutral,
  eased in and out (smoothstep), 30 fps;
* a held-out in-range performance: new combinations and asymmetric expressions, every
  weight within the training amplitudes;
* a held-out out-of-range performance: 20–40 % beyond the training amplitudes;
* held-out performances that need generalization: combinations no training clip shows
  (``heldout_combinations``: an asymmetric smile with one brow raised, pucker with the jaw
  open, squint with sneer, …, every weight within the training amplitudes) and every
  training expression amplified 25–40 % beyond its training amplitude
  (``heldout_amplified``); their noisy and occluded marker variants are made by
  :mod:`service.samples.capture_noise`;
* a long database performance (600+ frames) for shape-space methods (bermano2014 §4.1).

Every performance carries a small, smooth rigid head motion (rotation about a pivot in
the neck, translation), seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.spatial.transform import Rotation

FPS = 30.0
HEAD_PIVOT_MM = np.array([0.0, -60.0, 10.0])  # roughly the top of the neck

# name → blendshape weights at the peak of the training clip
TRAINING_EXPRESSIONS: dict[str, dict[str, float]] = {
    "brow_raise": {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 0.9,
                   "browOuterUp_R": 0.9, "eyeWide_L": 0.3, "eyeWide_R": 0.3},
    "brow_furrow": {"browDown_L": 1.0, "browDown_R": 1.0, "noseSneer_L": 0.25,
                    "noseSneer_R": 0.25, "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
    "smile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.7,
              "cheekSquint_R": 0.7, "eyeSquint_L": 0.4, "eyeSquint_R": 0.4},
    "squint": {"eyeSquint_L": 1.0, "eyeSquint_R": 1.0, "cheekSquint_L": 0.8,
               "cheekSquint_R": 0.8, "browDown_L": 0.3, "browDown_R": 0.3},
    "sneer": {"noseSneer_L": 1.0, "noseSneer_R": 1.0, "mouthUpperUp_L": 0.6,
              "mouthUpperUp_R": 0.6, "browDown_L": 0.4, "browDown_R": 0.4},
    "chin_raise": {"mouthShrugLower": 1.0, "mouthPress_L": 0.5, "mouthPress_R": 0.5,
                   "mouthFrown_L": 0.6, "mouthFrown_R": 0.6},
    "surprise": {"jawOpen": 0.7, "browInnerUp_L": 0.6, "browInnerUp_R": 0.6,
                 "browOuterUp_L": 0.6, "browOuterUp_R": 0.6, "eyeWide_L": 0.7, "eyeWide_R": 0.7},
    "pucker": {"mouthPucker": 1.0, "mouthFunnel": 0.4, "cheekPuff_L": 0.2, "cheekPuff_R": 0.2},
}

# held-out keyframes: new combinations, asymmetric, within the training amplitudes
IN_RANGE_KEYS: list[dict[str, float]] = [
    {},
    {"mouthSmile_L": 0.8, "cheekSquint_L": 0.6, "eyeSquint_L": 0.3},
    {"browInnerUp_L": 0.9, "browOuterUp_L": 0.8, "browInnerUp_R": 0.4, "browOuterUp_R": 0.3},
    {"browDown_L": 0.7, "browDown_R": 0.7, "eyeSquint_L": 0.5, "eyeSquint_R": 0.5,
     "cheekSquint_L": 0.4, "cheekSquint_R": 0.4},
    {"mouthSmile_L": 0.6, "mouthSmile_R": 0.6, "browInnerUp_L": 0.6, "browInnerUp_R": 0.6,
     "browOuterUp_L": 0.5, "browOuterUp_R": 0.5},
    {},
    {"noseSneer_R": 0.8, "mouthUpperUp_R": 0.5, "browDown_R": 0.4},
    {"mouthShrugLower": 0.7, "mouthFrown_L": 0.5, "mouthFrown_R": 0.3, "browInnerUp_L": 0.5,
     "browInnerUp_R": 0.5},
    {"mouthSmile_R": 0.9, "cheekSquint_R": 0.7, "eyeSquint_R": 0.8, "eyeSquint_L": 0.3},
    {"jawOpen": 0.5, "browInnerUp_L": 0.5, "browInnerUp_R": 0.5, "eyeWide_L": 0.5, "eyeWide_R": 0.5},
    {},
]

# held-out out-of-range keyframes: 20–40 % beyond the training amplitudes
OUT_OF_RANGE_KEYS: list[dict[str, float]] = [
    {},
    {"browInnerUp_L": 1.3, "browInnerUp_R": 1.3, "browOuterUp_L": 1.2, "browOuterUp_R": 1.2},
    {"mouthSmile_L": 1.3, "mouthSmile_R": 1.3, "cheekSquint_L": 0.95, "cheekSquint_R": 0.95,
     "eyeSquint_L": 0.55, "eyeSquint_R": 0.55},
    {"browDown_L": 1.35, "browDown_R": 1.35, "noseSneer_L": 0.35, "noseSneer_R": 0.35},
    {"mouthShrugLower": 1.3, "mouthFrown_L": 0.8, "mouthFrown_R": 0.8},
    {"eyeSquint_L": 1.3, "eyeSquint_R": 1.3, "cheekSquint_L": 1.1, "cheekSquint_R": 1.1},
    {},
]


# held-out combinations no training clip shows (each weight within the training amplitudes)
COMBINATION_KEYS: list[dict[str, float]] = [
    {},
    # asymmetric smile with the opposite brow raised
    {"mouthSmile_L": 0.9, "cheekSquint_L": 0.6, "browInnerUp_R": 0.8, "browOuterUp_R": 0.8},
    # pucker with the jaw open
    {"mouthPucker": 0.9, "mouthFunnel": 0.3, "jawOpen": 0.55},
    {},
    # squint with sneer
    {"eyeSquint_L": 0.9, "eyeSquint_R": 0.9, "cheekSquint_L": 0.6, "cheekSquint_R": 0.6,
     "noseSneer_L": 0.9, "noseSneer_R": 0.9, "mouthUpperUp_L": 0.5, "mouthUpperUp_R": 0.5},
    # laugh: smile with the jaw open
    {"mouthSmile_L": 0.85, "mouthSmile_R": 0.85, "cheekSquint_L": 0.5, "cheekSquint_R": 0.5,
     "jawOpen": 0.6},
    {},
    # brow furrow with pucker
    {"browDown_L": 0.9, "browDown_R": 0.9, "mouthPucker": 0.8},
    # one-sided sneer with the other brow raised
    {"noseSneer_R": 0.9, "mouthUpperUp_R": 0.5, "browInnerUp_L": 0.9, "browOuterUp_L": 0.8},
    {},
]

# training expressions amplified beyond their training amplitudes (factor drawn per key)
AMPLIFIED_EXPRESSIONS = ("brow_raise", "smile", "brow_furrow", "squint", "sneer", "surprise",
                         "chin_raise")
AMPLIFY_RANGE = (1.25, 1.40)


@dataclass(frozen=True)
class Performance:
    """One performance: per-frame blendshape weights and rigid head pose.

    Attributes
    ----------
    name : str
    kind : ``"training"``, ``"heldout_in_range"``, ``"heldout_out_of_range"`` or ``"database"``
    weights : (F,53) float           blendshape weights in rig order
    rotation : (F,3,3) float         head rotation about HEAD_PIVOT_MM
    translation : (F,3) float        head translation, mm
    fps : float
    """

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
        """Apply the per-frame head pose to head-frame positions X (F,n,3)."""
        out = np.empty(np.shape(X))
        for f, (R, t) in enumerate(zip(self.rotation, self.translation)):
            out[f] = (X[f] - HEAD_PIVOT_MM) @ R.T + (HEAD_PIVOT_MM + t)   # one GEMM a frame
        return out


def smoothstep(x: np.ndarray) -> np.ndarray:
    """3x² − 2x³ on [0,1] (ease in and out), clamped."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _weight_vector(names: tuple[str, ...], shape: dict[str, float]) -> np.ndarray:
    w = np.zeros(len(names))
    for k, v in shape.items():
        w[names.index(k)] = v
    return w


def keyframe_curve(keys: np.ndarray, frames_per_key: np.ndarray) -> np.ndarray:
    """Eased piecewise interpolation through keyframes.

    Parameters
    ----------
    keys : (K,C) float              keyframe values
    frames_per_key : (K-1,) int     frames spent moving from key k to key k+1

    Returns
    -------
    curve : (Σ frames_per_key + 1, C) float, starting at keys[0] and ending at keys[-1]
    """
    out = [keys[:1]]
    for k, n in enumerate(frames_per_key):
        t = smoothstep(np.arange(1, n + 1) / n)[:, None]
        out.append(keys[k] + t * (keys[k + 1] - keys[k]))
    return np.concatenate(out)


def head_motion(frames: int, rng: np.random.Generator, amplitude_deg: float = 3.0,
                amplitude_mm: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth small rigid head motion: sums of three random sinusoids per axis.

    Returns rotations (F,3,3) and translations (F,3) mm; frame 0 is close to identity
    but not exactly (a real capture never starts perfectly aligned).
    """
    t = np.arange(frames) / FPS
    freq = rng.uniform(0.1, 0.6, size=(2, 3, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(2, 3, 3))
    amp = rng.uniform(0.3, 1.0, size=(2, 3, 3))
    waves = (amp[..., None] * np.sin(2 * np.pi * freq[..., None] * t + phase[..., None])).sum(axis=2)
    waves /= amp.sum(axis=2)[..., None]
    rot = np.deg2rad(amplitude_deg) * waves[0].T            # (F,3) axis-angle
    trans = amplitude_mm * waves[1].T
    return Rotation.from_rotvec(rot).as_matrix(), trans


def training_clips(names: tuple[str, ...], seed: int, frames: int = 20) -> list[Performance]:
    """One clip per TRAINING_EXPRESSIONS entry: neutral → peak → neutral in ``frames``."""
    rng = np.random.default_rng([seed, 0x7C])
    clips = []
    rise = (frames - 4) // 2
    for name, shape in TRAINING_EXPRESSIONS.items():
        peak = _weight_vector(names, shape)
        keys = np.stack([np.zeros_like(peak), peak, peak, np.zeros_like(peak)])
        w = keyframe_curve(keys, np.array([rise, 3, frames - rise - 4]))
        R, t = head_motion(len(w), rng, amplitude_deg=2.0, amplitude_mm=2.0)
        clips.append(Performance(f"train_{name}", "training", w, R, t))
    return clips


def training_amplitudes(names: tuple[str, ...]) -> np.ndarray:
    """Largest weight (53,) each blendshape reaches in the training clips."""
    return np.max([_weight_vector(names, s) for s in TRAINING_EXPRESSIONS.values()], axis=0)


def _keyed_performance(names, keys, name, kind, rng, frames_per_key) -> Performance:
    K = np.stack([_weight_vector(names, k) for k in keys])
    spans = rng.integers(frames_per_key[0], frames_per_key[1] + 1, size=len(K) - 1)
    w = keyframe_curve(K, spans)
    R, t = head_motion(len(w), rng)
    return Performance(name, kind, w, R, t)


def heldout_in_range(names: tuple[str, ...], seed: int) -> Performance:
    """New combinations and asymmetric expressions within the training amplitudes."""
    rng = np.random.default_rng([seed, 0x1A])
    return _keyed_performance(names, IN_RANGE_KEYS, "heldout_in_range", "heldout_in_range",
                              rng, (12, 18))


def heldout_out_of_range(names: tuple[str, ...], seed: int) -> Performance:
    """Expressions 20–40 % beyond the training amplitudes."""
    rng = np.random.default_rng([seed, 0x0A])
    return _keyed_performance(names, OUT_OF_RANGE_KEYS, "heldout_out_of_range",
                              "heldout_out_of_range", rng, (12, 18))


def heldout_combinations(names: tuple[str, ...], seed: int) -> Performance:
    """Combinations no training clip shows (COMBINATION_KEYS), within the training amplitudes."""
    rng = np.random.default_rng([seed, 0xC0])
    return _keyed_performance(names, COMBINATION_KEYS, "heldout_combinations",
                              "heldout_combinations", rng, (12, 18))


def amplified_keys(seed: int) -> list[dict[str, float]]:
    """Keyframes: each of AMPLIFIED_EXPRESSIONS × a seeded factor in AMPLIFY_RANGE, neutral at the ends."""
    rng = np.random.default_rng([seed, 0xA3])
    factor = rng.uniform(*AMPLIFY_RANGE, size=len(AMPLIFIED_EXPRESSIONS))
    keys = [{k: v * f for k, v in TRAINING_EXPRESSIONS[name].items()}
            for name, f in zip(AMPLIFIED_EXPRESSIONS, factor)]
    return [{}, *keys, {}]


def heldout_amplified(names: tuple[str, ...], seed: int) -> Performance:
    """Every AMPLIFIED_EXPRESSIONS entry 25–40 % beyond its training amplitude, one after another."""
    rng = np.random.default_rng([seed, 0xA4])
    return _keyed_performance(names, amplified_keys(seed), "heldout_amplified",
                              "heldout_out_of_range", rng, (12, 18))


def database_performance(names: tuple[str, ...], seed: int, frames: int = 630) -> Performance:
    """A long performance: random blends of the training expressions plus speech-like jaw.

    Keyframes every 12–24 frames pick one or two training expressions at random
    amplitudes in [0.3, 1] of their peak (sometimes one side only); a smooth jaw signal
    (0–0.35) is added as talking. Weights stay within the training amplitudes.
    """
    rng = np.random.default_rng([seed, 0xDB])
    shapes = list(TRAINING_EXPRESSIONS.values())
    keys, spans = [np.zeros(len(names))], []
    while sum(spans) < frames - 1:
        w = np.zeros(len(names))
        for idx in rng.choice(len(shapes), size=rng.integers(1, 3), replace=False):
            peak = _weight_vector(names, shapes[idx]) * rng.uniform(0.3, 1.0)
            side = rng.choice(["both", "both", "_L", "_R"])
            if side != "both":
                other = "_R" if side == "_L" else "_L"
                peak[[i for i, n in enumerate(names) if n.endswith(other)]] *= rng.uniform(0, 0.4)
            w = np.maximum(w, peak)
        keys.append(w)
        spans.append(int(rng.integers(12, 25)))
    spans[-1] -= sum(spans) - (frames - 1)
    W = keyframe_curve(np.stack(keys), np.array(spans))
    # talking: a jaw oscillation whose rate drifts between 2 and 4 Hz
    rate = np.interp(np.arange(frames), np.linspace(0, frames, 12), rng.uniform(2.0, 4.0, 12))
    jaw = 0.175 * (1 - np.cos(2 * np.pi * np.cumsum(rate) / FPS))
    j = names.index("jawOpen")
    W[:, j] = np.maximum(W[:, j], jaw)
    W = np.minimum(W, training_amplitudes(names))
    R, t = head_motion(frames, rng)
    return Performance("database", "database", W, R, t)
