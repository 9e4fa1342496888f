"""A WPSD model at a higher mesh level for the speed rows of ``pose_space_report.py`` without
training at that level: a WPSD of a lower level (``--speed-only --train-missing`` saved it)
transferred (bickel2008 §5.4) to the higher-level mesh of the same identity (seed 1); 40
landmark pairs = farthest-point face vertices of the source level and their nearest target
vertices (``harness.face_landmarks``). The model keeps the source's map size. Its
``.train.json`` holds the transfer time (not a training time).

Usage: ``python benchmarks/pose_space_l2_speed_model.py SOURCE_MODEL_DIR SOURCE_ACTOR
TARGET_ACTOR OUT_MODEL_DIR`` (e.g. a level-1 or level-0 model, its actor, a level-2 actor);
then ``pose_space_report.py TARGET_ACTOR --speed-only`` with OUT_MODEL_DIR under its
``models/<actor>/``.
"""

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import harness as pr  # noqa: E402  (the reports' shared code; no report imports another)


def main() -> None:
    from service.methods.pose_space import PoseSpaceModel
    from service.methods.pose_space.transfer import transfer
    from service.samples.dataset import load_actor

    src_dir, l1_dir, l2_dir, out = (Path(a) for a in sys.argv[1:5])
    src = PoseSpaceModel.load(src_dir)
    a1, a2 = load_actor(l1_dir), load_actor(l2_dir)
    lm1 = pr.face_landmarks(a1)
    _, lm2 = cKDTree(a2.vertices).query(a1.vertices[lm1])
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    moved = transfer(src, a2, np.stack([lm1, lm2], 1))
    seconds = time.perf_counter() - t0
    moved.save(out)
    out.with_suffix(".train.json").write_text(json.dumps(
        {"train_s": seconds, "transfer_from": str(src_dir), "load_average": [load0, os.getloadavg()[0]]}))
    print(json.dumps({"transfer_s": seconds, "vertices": moved.data.n_vertices, **moved.metrics["transfer"]}))


if __name__ == "__main__":
    main()
