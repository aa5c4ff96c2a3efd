"""PLAD rounds: P_BEST updates, training from the sources, resume after a kill."""
import json

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.finetune import FinetuneConfig, finetune
from plad.model import ModelConfig, PLADNet
from plad.pbest import PBest
from plad.train import TrainConfig

DOMAIN = get_domain("csg2d")


def tiny_model(seed=0):
    torch.manual_seed(seed)
    return PLADNet(ModelConfig(vocab_size=len(DOMAIN.tokens), max_len=DOMAIN.tokens.max_len,
                               input_shape=DOMAIN.shape, d_model=32, n_layers=1, n_heads=2, dim_ff=64,
                               enc_channels=(4, 8, 8, 16)))


@pytest.fixture(scope="module")
def shapes():
    progs = DOMAIN.sample(72, np.random.default_rng(11))
    x = DOMAIN.execute(pad_programs(progs)).numpy()
    return x[:48], x[48:]


def config(method="lest+st", rounds=2):
    return FinetuneConfig(method=method, infer_beam=2, infer_batch=24, val_beam_epoch=1, val_beam_round=2,
                          max_rounds=rounds, round_patience=100,
                          train=TrainConfig(batch_size=16, lr=1e-3, steps_per_epoch=3, max_epochs=2, patience=5))


def test_rounds_update_pbest_and_write_their_state(tmp_path, shapes):
    train, val = shapes
    summary = finetune(tiny_model(), DOMAIN, train, val, config(), tmp_path)
    assert summary["rounds"] == 2 and summary["stopped"] == "max_rounds"
    state = json.loads((tmp_path / "state.json").read_text())
    means = [r["pbest_mean"] for r in state["history"][1:]]
    assert len(means) == 2 and means[1] <= means[0] + 1e-12  # all-time P_BEST never gets worse
    pbest = PBest.load(tmp_path / "pbest.npz", DOMAIN.metric)
    assert pbest.has.all()
    again = DOMAIN.execute(pad_programs([pbest.program(i) for i in range(len(pbest))])).numpy()
    assert np.array_equal(again, pbest.executions)


def test_resume_after_a_kill_continues_identically(tmp_path, shapes):
    train, val = shapes
    finetune(tiny_model(), DOMAIN, train, val, config(rounds=2), tmp_path / "straight")
    finetune(tiny_model(), DOMAIN, train, val, config(rounds=1), tmp_path / "killed")   # stops after round 1
    finetune(tiny_model(seed=5), DOMAIN, train, val, config(rounds=2), tmp_path / "killed")  # the same command again
    a = torch.load(tmp_path / "straight" / "current.pt", weights_only=False)["state_dict"]
    b = torch.load(tmp_path / "killed" / "current.pt", weights_only=False)["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    pa = PBest.load(tmp_path / "straight" / "pbest.npz", DOMAIN.metric)
    pb = PBest.load(tmp_path / "killed" / "pbest.npz", DOMAIN.metric)
    assert np.array_equal(pa.programs, pb.programs)


def test_wake_sleep_is_refused_until_it_exists(tmp_path, shapes):
    with pytest.raises(NotImplementedError):
        finetune(tiny_model(), DOMAIN, *shapes, config(method="lest+st+ws"), tmp_path)
