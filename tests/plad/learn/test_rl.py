"""The REINFORCE baseline: rewards, masked sampling, policy log-probabilities, one update."""
import json
import math

import numpy as np
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.job import Job
from plad.learn.loop import budget_seconds
from plad.learn.rl import Reinforce, RLConfig, masked_log_probs, reward, run_rl, sample_programs

DOMAIN = get_domain("csg2d")


def targets(n=8):
    return DOMAIN.execute(pad_programs(DOMAIN.sample(n, np.random.default_rng(0))))


def test_2d_reward_is_csgnets_transform_of_the_chamfer_distance():
    cd = torch.tensor([0.0, 1.0, 64 * math.sqrt(2), 100.0], dtype=torch.float64)
    r = reward(DOMAIN, cd)
    assert r[0] == 1 and r[2] == 0 and r[3] == 0
    assert abs(float(r[1]) - (1 - 1 / (64 * math.sqrt(2))) ** 20) < 1e-12


def test_sampled_programs_are_valid_and_log_probs_match_the_decoder(tiny_model):
    model = tiny_model().eval()
    x = targets()
    tokens, lengths = sample_programs(model, DOMAIN, x, torch.Generator().manual_seed(0))
    for row, n in zip(tokens, lengths):
        DOMAIN.check(row[: int(n)].tolist())
    with torch.no_grad():
        teacher = masked_log_probs(model, DOMAIN, x, tokens, lengths)
        # the same sum, step by step with the incremental decoder and the grammar mask
        logits, caches = model.start(model.encode(x))
        state = DOMAIN.tokens.initial_state(len(x))
        total = torch.zeros(len(x))
        for pos in range(tokens.shape[1]):
            live = pos < lengths
            logp = torch.log_softmax(logits.masked_fill(~DOMAIN.tokens.mask(state), float("-inf")), -1)
            total += torch.where(live, logp.gather(1, tokens[:, pos:pos + 1])[:, 0], torch.zeros(len(x)))
            state = DOMAIN.tokens.advance(state, tokens[:, pos])
            if pos + 1 < tokens.shape[1]:
                logits, caches = model.step(tokens[:, pos], caches, pos + 1)
    assert torch.allclose(teacher, total, atol=1e-4)


def test_one_update_moves_the_weights_and_the_baseline(tiny_model):
    model = tiny_model()
    learner = Reinforce(model, DOMAIN, RLConfig(lr=0.01, batch_size=8, baseline_alpha=0.7), seed=0)
    before = [p.detach().clone() for p in model.parameters()]
    x = targets()
    first = learner.step(x)
    assert first["baseline"] == first["reward"]
    second = learner.step(x)
    assert abs(second["baseline"] - (0.7 * first["reward"] + 0.3 * second["reward"])) < 1e-9
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters()))
    assert 0 <= second["reward"] <= 1


def rl_config(epochs):
    return RLConfig(lr=1e-2, batch_size=8, steps_per_epoch=2, max_epochs=epochs, val_beam=2, val_batch=8)


def rl(model, train, val, cfg, out, seed=0, max_minutes=None):
    return run_rl(Job(model, DOMAIN, train, val, out, seed=seed, budget_seconds=budget_seconds(max_minutes)),
                  cfg)


def test_rl_training_selects_on_validation_and_resumes_identically(tmp_path, tiny_model):
    train, val = targets(24).numpy(), targets(8).numpy()
    summary = rl(tiny_model(), train, val, rl_config(3), tmp_path / "straight", seed=1)
    assert summary["units"] == 3 and summary["unit_name"] == "epoch" and summary["stopped"] == "max_epochs"
    state = json.loads((tmp_path / "straight" / "state.json").read_text())
    vals = [r["val"] for r in state["history"]]
    assert [r["unit"] for r in state["history"]] == [0, 1, 2, 3]
    assert state["best"] == vals[state["best_unit"]] and state["best"] <= vals[0]
    best = torch.load(tmp_path / "straight" / "best.pt", weights_only=False)
    assert best["unit"] == state["best_unit"]
    rl(tiny_model(), train, val, rl_config(1), tmp_path / "killed", seed=1)
    torch.manual_seed(123)  # the resumed run must not depend on the global RNG
    rl(tiny_model(), train, val, rl_config(3), tmp_path / "killed", seed=1)
    a = torch.load(tmp_path / "straight" / "learner.pt", weights_only=False)
    b = torch.load(tmp_path / "killed" / "learner.pt", weights_only=False)
    for k in a["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k
    assert a["baseline"] == b["baseline"]


def test_rl_budget_stops_after_one_epoch(tmp_path, tiny_model):
    train, val = targets(24).numpy(), targets(8).numpy()
    summary = rl(tiny_model(), train, val, rl_config(100), tmp_path, max_minutes=1e-5)
    assert summary["stopped"] == "budget" and summary["units"] == 1
