"""A small flat 'face' with two expression clips and maps, for the stress-blend tests."""

import numpy as np

from service.methods.inputs import ActorData, Clip

N = 13                       # vertices per side
SIZE = 30.0                  # mm
H = 32                       # map size


def grid():
    x, y = np.meshgrid(np.linspace(0, SIZE, N), np.linspace(0, SIZE, N))
    V = np.column_stack([x.ravel(), y.ravel(), np.zeros(N * N)])
    i = np.arange(N - 1)
    a = (i[:, None] * N + i[None, :]).ravel()
    F = np.concatenate([np.column_stack([a, a + 1, a + N + 1]), np.column_stack([a, a + N + 1, a + N])])
    uv = 0.05 + 0.9 * V[:, :2] / SIZE
    return V, F, uv


def actor() -> ActorData:
    V, F, uv = grid()
    return ActorData(V, F, uv, F.copy(), np.array([0, 50, 100]), np.full((3, 3), 1 / 3),
                     ("a", "b", "c"), {"face": np.ones(len(V), bool)})


def deform(V, kind, amount):
    """'stretch': the left half stretches along x; 'squeeze': the top half compresses along y."""
    X = V.copy()
    if kind == "stretch":
        s = np.clip(V[:, 0] / (SIZE / 2), 0, 1)
        X[:, 0] = V[:, 0] + amount * 0.3 * (SIZE / 2) * np.minimum(V[:, 0], SIZE / 2) / (SIZE / 2)
        X[:, 0] += amount * 0.3 * (SIZE / 2) * (V[:, 0] > SIZE / 2) * 0
        X[:, 2] = amount * 0.5 * s * 0
    else:
        top = np.clip((V[:, 1] - SIZE / 2) / (SIZE / 2), 0, 1)
        X[:, 1] = V[:, 1] - amount * 0.25 * (SIZE / 2) * top ** 2
    return X


def clips(seed=0, frames=5):
    a = actor()
    rng = np.random.default_rng(seed)
    out = []
    for name, kind in (("train_stretch", "stretch"), ("train_squeeze", "squeeze")):
        amounts = np.sin(np.linspace(0, np.pi, frames))        # neutral → peak → neutral
        R = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
        verts = np.stack([deform(a.vertices, kind, s) @ R.T + [5, -3, 2] for s in amounts])
        disp = rng.normal(scale=0.1, size=(frames, H, H)).astype(np.float32)
        alb = rng.uniform(0.2, 0.8, size=(frames, H, H, 3)).astype(np.float32)
        markers = np.stack([a.marker_positions(v) for v in verts])
        out.append(Clip(name, verts, markers, disp, alb, 30.0))
    return a, out
