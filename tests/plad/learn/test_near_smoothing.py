"""The near-miss loss (``train.near_smoothing``, issue 58): a target token's probability partly on the tokens one
grid step from it, so that a near miss costs less than a far one; 0 is the plain cross-entropy of every run before.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from plad.config import ConfigError, build
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.domains.grammar import near_matrix, near_targets
from plad.layout import LAST, Layout
from plad.learn.pretrain import PretrainConfig, pretrain
from plad.learn.train import TrainConfig
from plad.model.checkpoint import read_checkpoint
from plad.model.network import Architecture, ModelConfig, PLADNet
from tests.tiny import ARCHITECTURE


def test_a_number_shares_its_mass_with_its_neighbours_and_an_operator_keeps_its_own():
    tokens = get_domain("csg3d").tokens.tokens
    soft = near_targets(tokens, 0.2)
    assert soft.shape == (len(tokens), len(tokens))
    torch.testing.assert_close(soft.sum(1), torch.ones(len(tokens)))
    near = near_matrix(tokens)
    for a in range(len(tokens)):
        others = [b for b in range(len(tokens)) if near[a, b] and b != a]
        row = soft[a]
        if others:      # 0.8 on itself, 0.2 shared evenly by its neighbours, nothing elsewhere
            assert row[a].item() == pytest.approx(0.8)
            assert row[others].tolist() == pytest.approx([0.2 / len(others)] * len(others))
            assert row.sum().item() - row[a].item() - row[others].sum().item() == pytest.approx(0.0, abs=1e-7)
        else:
            assert row[a].item() == 1.0 and row.sum().item() == 1.0
    # a 3D number's neighbours are the numbers one step below and above it (the end values have one); a
    # primitive and an operator (their parameter a name) have none
    counts = {t.kind: sorted({int((near[a].sum() - 1).item()) for a, u in enumerate(tokens) if u.kind == t.kind})
              for t in tokens if t.params}
    assert counts == {"num": [1, 2], "primitive": [0], "operator": [0]}


def test_zero_smoothing_is_the_identity_and_a_bad_share_is_refused():
    tokens = get_domain("shapeassembly").tokens.tokens
    assert torch.equal(near_targets(tokens, 0.0), torch.eye(len(tokens)))
    with pytest.raises(ValueError, match="expected 0 <= smoothing < 1"):
        near_targets(tokens, 1.0)
    with pytest.raises(ConfigError, match="near_smoothing -0.1: expected 0 <= near_smoothing < 1"):
        build(TrainConfig, {"near_smoothing": -0.1}, "teach.csg3d.train")


def test_the_soft_loss_is_the_cross_entropy_against_the_soft_rows():
    torch.manual_seed(0)
    domain = get_domain("csg3d")
    model = PLADNet(ModelConfig.for_domain(Architecture(**ARCHITECTURE), domain)).eval()
    progs = domain.samplers()["paper"](4, np.random.default_rng(0))
    programs, lengths = pad_programs(progs), torch.tensor([len(p) for p in progs])
    shapes = domain.execute(programs)
    plain, acc = model.loss(shapes, programs, lengths)
    same, acc_same = model.loss(shapes, programs, lengths, soft=torch.eye(len(domain.tokens.tokens)))
    torch.testing.assert_close(same, plain)
    assert acc_same == acc
    soft = near_targets(domain.tokens.tokens, 0.3)
    smoothed, acc_soft = model.loss(shapes, programs, lengths, soft=soft)
    assert acc_soft == acc                                 # the accuracy still counts the token itself
    logits, target, valid = model.teacher_forced(model.encode(shapes), programs, lengths)
    logp = torch.log_softmax(logits, -1)
    expected = -(soft[target] * logp).sum(-1)[valid].mean()
    torch.testing.assert_close(smoothed, expected)
    assert smoothed.item() != pytest.approx(plain.item())


@pytest.fixture(scope="module")
def programs(tmp_path_factory):
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    root = tmp_path_factory.mktemp("programs")
    synthesize(SynthesizeConfig(domain="csg3d", train_programs=64, val_programs=8, seed=3), Layout(root))
    return root


def pretrained(programs, tmp_path, name, smoothing):
    root = tmp_path / name
    shutil.copytree(programs / "data", root / "data")
    cfg = PretrainConfig(domain="csg3d", device="cpu", threads=1, val_metric_shapes=2, gap_programs=2,
                         model=Architecture(**ARCHITECTURE),
                         train=TrainConfig(batch_size=8, steps_per_epoch=3, max_epochs=1, lr=1e-3, patience=10,
                                           near_smoothing=smoothing))
    summary = pretrain(cfg, Layout(root))
    return summary, read_checkpoint(Layout(root).pretrain_dir("csg3d") / LAST)


def test_training_with_it_takes_other_steps_and_says_so_in_its_fingerprint(programs, tmp_path):
    plain, a = pretrained(programs, tmp_path, "plain", 0.0)
    soft, b = pretrained(programs, tmp_path, "soft", 0.2)
    _, c = pretrained(programs, tmp_path, "again", 0.0)
    assert "near_smoothing" not in a["fingerprint"]          # the plain loss: the fingerprint of earlier runs
    assert b["fingerprint"]["near_smoothing"] == 0.2
    assert {k: v for k, v in b["fingerprint"].items() if k != "near_smoothing"} == a["fingerprint"]
    for key in a["state_dict"]:                                   # the same data and seeds, other steps
        if not torch.equal(a["state_dict"][key], b["state_dict"][key]):
            break
    else:
        pytest.fail("the near-miss loss trained the same weights as the plain one")
    for key in a["state_dict"]:                                   # the plain loss is deterministic: same weights again
        assert torch.equal(a["state_dict"][key], c["state_dict"][key])
    assert plain["val_loss"] != soft["val_loss"]
