"""The pdm-train / pdm-synthesize commands on the level-0 sample actor."""

import numpy as np

from service.cli import main


def test_pdm_train_and_synthesize_from_the_command_line(pdm_actor_dir, tmp_path, capsys):
    model = tmp_path / "model"
    assert main(["pdm-train", "--actor", str(pdm_actor_dir), "--out", str(model), "--clips",
                 "train_smile", "train_brow_raise", "--medium-resolution", "64",
                 "--fine-resolution", "64", "--order", "linear"]) == 0
    assert "PCA energy" in capsys.readouterr().out
    with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
        np.savez(tmp_path / "m.npz", markers=d["markers"][:10])
    assert main(["pdm-synthesize", "--model", str(model), "--markers", str(tmp_path / "m.npz"),
                 "--out", str(tmp_path / "out.npz"), "--outputs", "mesh,displacement"]) == 0
    with np.load(tmp_path / "out.npz") as d:
        assert d["vertices"].shape == (10, 11248, 3) and d["displacement"].shape == (10, 64, 64)
        assert np.isfinite(d["vertices"]).all()
