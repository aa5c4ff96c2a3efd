"""PLAD rounds: P_BEST updates, training from the sources, resume after a kill."""
import json

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.job import Job
from plad.learn.loop import budget_seconds
from plad.learn.methods import MethodConfig
from plad.learn.pbest import PBest
from plad.learn.rounds import RoundsConfig, run_rounds
from plad.learn.train import TrainConfig
from plad.learn.ws import WSConfig, new_generator, sample_dataset, train_generator

DOMAIN = get_domain("csg2d")


@pytest.fixture(scope="module")
def shapes():
    progs = DOMAIN.sample(72, np.random.default_rng(11))
    x = DOMAIN.execute(pad_programs(progs)).numpy()
    return x[:48], x[48:]


def config(rounds=2):
    return RoundsConfig(infer_beam=2, infer_batch=24, val_beam_epoch=1, val_beam_round=2,
                        max_rounds=rounds, round_patience=100,
                        train=TrainConfig(batch_size=16, lr=1e-3, steps_per_epoch=3, max_epochs=2, patience=5),
                        ws=WSConfig(latent=8, hidden=16, batch_size=16, max_epochs=3, sample_batch=64))


def rounds(model, shapes, method, cfg, out, max_minutes=None, pbest_mode="all-time"):
    train, val = shapes
    job = Job(model, DOMAIN, train, val, out, budget_seconds=budget_seconds(max_minutes))
    return run_rounds(job, MethodConfig(method, pbest_mode), cfg)


def test_rounds_update_pbest_and_write_their_state(tmp_path, shapes, tiny_model):
    summary = rounds(tiny_model(), shapes, "lest+st", config(), tmp_path)
    assert summary["units"] == 2 and summary["unit_name"] == "round" and summary["stopped"] == "max_rounds"
    state = json.loads((tmp_path / "state.json").read_text())
    assert [r["unit"] for r in state["history"]] == [0, 1, 2]
    vals = [r["val"] for r in state["history"]]
    assert summary["val"] == min(vals) == vals[summary["best_unit"]]   # Chamfer: lower is better
    means = [r["pbest_mean"] for r in state["history"][1:]]
    assert len(means) == 2 and means[1] <= means[0] + 1e-12  # all-time P_BEST never gets worse
    pbest = PBest.load(tmp_path / "pbest.npz", DOMAIN.metric)
    assert pbest.has.all()
    again = DOMAIN.execute(pad_programs([pbest.program(i) for i in range(len(pbest))])).numpy()
    assert np.array_equal(again, pbest.executions)


def test_the_method_sets_the_pbest_mode(tmp_path, shapes, tiny_model):
    rounds(tiny_model(), shapes, "lest+st", config(rounds=1), tmp_path, pbest_mode="per-round")
    assert PBest.load(tmp_path / "pbest.npz", DOMAIN.metric).mode == "per-round"


@pytest.mark.parametrize("method", ["lest+st", "lest+st+ws"])
def test_resume_after_a_kill_continues_identically(tmp_path, shapes, method, tiny_model):
    straight = rounds(tiny_model(), shapes, method, config(rounds=2), tmp_path / "straight")
    rounds(tiny_model(), shapes, method, config(rounds=1), tmp_path / "killed")  # stops after round 1
    # the same command again, with another initial model: everything comes from disk
    resumed = rounds(tiny_model(seed=5), shapes, method, config(rounds=2), tmp_path / "killed")
    assert {k: v for k, v in straight.items() if k != "train_seconds"} == \
        {k: v for k, v in resumed.items() if k != "train_seconds"}
    a = torch.load(tmp_path / "straight" / "current.pt", weights_only=False)["state_dict"]
    b = torch.load(tmp_path / "killed" / "current.pt", weights_only=False)["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    pa = PBest.load(tmp_path / "straight" / "pbest.npz", DOMAIN.metric)
    pb = PBest.load(tmp_path / "killed" / "pbest.npz", DOMAIN.metric)
    assert np.array_equal(pa.programs, pb.programs)


def test_wake_sleep_generator_learns_and_samples_unique_nonempty_programs(shapes, tiny_model):
    train, _ = shapes
    model = tiny_model()
    pbest = PBest(len(train), DOMAIN.shape, DOMAIN.tokens.max_len, DOMAIN.metric)
    progs = DOMAIN.sample(len(train), np.random.default_rng(3))
    pbest.update(np.arange(len(train)), progs, np.ones(len(train)), DOMAIN.execute(pad_programs(progs)).numpy())
    cfg = WSConfig(latent=8, hidden=16, batch_size=16, max_epochs=1, sample_batch=64)
    gen = new_generator(model, cfg)
    first = train_generator(gen, pbest, cfg, seed=0)["ws_loss"]
    later = train_generator(gen, pbest, WSConfig(**{**cfg.__dict__, "max_epochs": 15}), seed=1)["ws_loss"]
    assert later < first  # the ELBO loss goes down on P_BEST
    programs, executions, stats = sample_dataset(gen, DOMAIN, 40, cfg, seed=0)
    assert len(programs) == 40 and stats["ws_unique"] == 1.0
    assert len({p.tobytes() for p in programs}) == 40
    rows = [p[p >= 0].tolist() for p in programs]
    for r in rows:
        DOMAIN.check(r)
    assert executions.reshape(40, -1).any(1).all()
    # WS pairs execute exactly to their shapes
    assert np.array_equal(DOMAIN.execute(pad_programs(rows)).numpy(), executions)


def test_wake_sleep_rounds_write_generator_and_samples(tmp_path, shapes, tiny_model):
    summary = rounds(tiny_model(), shapes, "lest+st+ws", config(rounds=1), tmp_path)
    assert summary["units"] == 1
    assert (tmp_path / "ws_generator.pt").exists() and (tmp_path / "ws_round_001.npz").exists()
    row = json.loads((tmp_path / "state.json").read_text())["history"][1]
    assert row["ws_unique"] > 0 and 0 <= row["ws_empty_share"] <= 1


def test_budget_stops_rounds(tmp_path, shapes, tiny_model):
    summary = rounds(tiny_model(), shapes, "st", config(rounds=50), tmp_path, max_minutes=1e-4)
    assert summary["stopped"] == "budget" and summary["units"] == 1
