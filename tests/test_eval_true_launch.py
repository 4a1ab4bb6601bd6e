"""The law alone, from the true launch: chamfer_from_launch against a known trajectory (session 21: the per-seed
launch estimate ranked Table 1's CDs with rho 0.92, so the evaluation also rolls each law out from the truth)."""

import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, ground_truth_views, tiny_body, tiny_solver  # noqa: E402

from gca.eval.evaluate import chamfer_from_launch  # noqa: E402
from gca.laws.presets import material_from_preset  # noqa: E402
from gca.scenes import truth  # noqa: E402

V_TRUE = (0.6, -1.2, 0.0)


def _scene(tmp: Path, body, frames, x) -> Path:
    scene, gt = tmp / "scene", tmp / "gt"
    scene.mkdir()
    gt.mkdir()
    (scene / "meta.json").write_text(json.dumps({"video_frames": frames, "substeps": 2, "dt": tiny_solver().cfg.dt}))
    np.savez(gt / "trajectory.npz", x=x[[0] + frames].numpy())
    return scene


def test_the_true_launch_reproduces_the_truth_and_a_wrong_one_does_not(tmp_path):
    torch.manual_seed(0)
    body = tiny_body()
    _, frames, x = ground_truth_views(body, V_TRUE, n_frames=8, frame_every=2)
    scene = _scene(tmp_path, body, frames, x)
    law = material_from_preset(JELLY)  # the true law: from the true launch its rollout is the truth
    with truth.bind(scene, tmp_path / "gt"):
        exact = chamfer_from_launch(tiny_solver(), law, body, (list(V_TRUE), [0.0, 0.0, 0.0]), scene)
        off = chamfer_from_launch(tiny_solver(), law, body, ([0.6, -1.2, 1.5], [0.0, 0.0, 0.0]), scene)
    assert exact < 1e-5  # the same deterministic CPU rollout
    assert off > 100 * max(exact, 1e-6)  # negative control: 1.5 m/s along z moves the body by centimetres
