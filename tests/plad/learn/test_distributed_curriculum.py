"""Pretraining with the curriculum under torchrun (2 CPU processes): equal ranks, and a resume in its stage."""
from __future__ import annotations

import pytest
import torch

from plad.layout import HISTORY, LAST, Layout
from tests.procs import children, launch, left_behind
from tests.tiny import tiny_pretrain_params

pytestmark = pytest.mark.integration

CURRICULUM = ["curriculum.enabled=true", "curriculum.stages=[2]", "curriculum.stage_steps=4",
              "curriculum.replay=0.5", "train.warmup_steps=3", "model.prefix_bos=true", "model.enc_init=kaiming"]


def test_two_process_curriculum_keeps_ranks_equal_and_resumes_in_its_stage(tmp_path, synthetic):
    before = children()
    tiny_pretrain_params(tmp_path / "params.yaml")
    straight, resumed = Layout(tmp_path / "straight"), Layout(tmp_path / "resumed")
    for layout in (straight, resumed):
        layout.synthetic_dir.parent.mkdir(parents=True)
        layout.synthetic_dir.symlink_to(synthetic)

    def stage(root: str, *sets: str) -> list[str]:
        return ["pretrain", "--params", "params.yaml", "--section", "pretrain.csg2d", "--root", root,
                *[f"--set {s}" for s in (*CURRICULUM, *sets)]]

    (r0, r1), first = launch(tmp_path, "first", [stage("straight"), stage("resumed", "train.max_epochs=1")])
    [second] = launch(tmp_path, "second", [stage("resumed")])
    assert len(r0["steps"]) == 2 * 4 and r0["steps"] == r1["steps"]   # equal weights after every step
    for rank in (0, 1):
        assert first[rank]["steps"] + second[rank]["steps"] == r0["steps"]
    last = torch.load(straight.pretrain_dir("csg2d") / LAST, weights_only=False)
    assert last["stages"]["stage"] == 1   # 4 steps in the first stage, then the final one
    lines = (straight.pretrain_dir("csg2d") / HISTORY).read_text().splitlines()
    assert "curriculum_stage" in lines[0].split(",") and len(lines) == 3
    assert left_behind(before) == []
