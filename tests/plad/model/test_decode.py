"""p(z|x), checkpoints, resumable training, beam search (generic; exercised on 2D CSG)."""
import dataclasses

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.train import FitSetup, TrainConfig, fit
from plad.model.checkpoint import CheckpointError, load_model, save_checkpoint
from plad.model.decode import beam_search, greedy_decode, infer_programs
from plad.model.network import Architecture, ModelConfig, PLADNet
from tests.tiny import tiny_config

DOMAIN = get_domain("csg2d")


def synthetic_batches(programs, batch_size=64, seed=0):
    train = pad_programs(programs, pad=-1)

    def batches(epoch):
        gen = torch.Generator().manual_seed(seed * 1000 + epoch)
        while True:
            perm = torch.randperm(len(train), generator=gen)
            for s in range(0, len(perm) - batch_size + 1, batch_size):
                p = train[perm[s:s + batch_size]]
                lengths = (p >= 0).sum(1)
                p = p.clamp(min=0)
                yield DOMAIN.execute(p), p, lengths
    return batches


@pytest.fixture(scope="module")
def programs():
    return DOMAIN.sample(3000, np.random.default_rng(0))


@pytest.fixture(scope="module")
def trained(tmp_path_factory, programs):
    """A tiny model trained briefly on synthetic programs, with its training history."""
    torch.manual_seed(0)
    model = PLADNet(tiny_config())
    val = synthetic_batches(programs[-256:], batch_size=256)(0)
    val_batch = next(val)
    history = []

    def validate(m):
        m.eval()
        with torch.no_grad():
            loss, acc = m.loss(*val_batch)
        return {"val_loss": float(loss), "val_acc": float(acc)}

    out = tmp_path_factory.mktemp("tiny")
    result = fit(model, synthetic_batches(programs[:-256]), validate,
                 TrainConfig(batch_size=64, lr=3e-3, steps_per_epoch=40, max_epochs=5, patience=5),
                 out, FitSetup("csg2d", DOMAIN.tokens.names, on_unit=lambda e, row: history.append(row)))
    return model, history, result, out


def test_incremental_decoding_matches_teacher_forcing():
    torch.manual_seed(0)
    for shape in [(64, 64), (32, 32, 32)]:
        model = PLADNet(tiny_config(input_shape=shape)).eval()
        x = torch.rand(3, *shape) > 0.5
        tokens = torch.randint(0, model.cfg.vocab_size, (3, 6))
        tokens_in = torch.cat([torch.full((3, 1), model.cfg.bos), tokens[:, :-1]], 1)
        with torch.no_grad():
            full = model(x, tokens_in)
            logits, caches = model.start(model.encode(x))
            steps = [logits]
            for i in range(5):
                logits, caches = model.step(tokens[:, i], caches, i + 1)
                steps.append(logits)
        assert torch.allclose(full, torch.stack(steps, 1), atol=1e-5)


def test_reordered_caches_decode_as_the_selected_rows_alone():
    """KVCache.select: gathering rows in place (same row count, a beam step) or into a new cache (more
    rows, the first beam step) gives each row the logits it gets when decoded on its own."""
    torch.manual_seed(0)
    model = PLADNet(tiny_config(input_shape=(32, 32, 32))).eval()
    x = torch.rand(3, 32, 32, 32) > 0.5
    tokens = torch.randint(0, model.cfg.vocab_size, (3, 4))
    with torch.no_grad():
        prefix = model.encode(x)

        def decode(rows, reorder_at):
            logits, caches = model.start(prefix)
            toks = tokens
            for i in range(4):
                if i == reorder_at:
                    caches = [c.select(rows) for c in caches]
                    toks = tokens[rows]
                logits, caches = model.step(toks[:, i], caches, i + 1)
            return logits

        # [0, 0, 2]: rows that keep their own hypothesis are not copied (only row 1 is written)
        for rows in (torch.tensor([2, 0, 0]), torch.tensor([0, 0, 2]), torch.tensor([1, 1, 2, 0, 2])):
            for reorder_at in (0, 2):
                alone = decode(torch.arange(3), None)[rows]
                # tokens before the reordering come from the original rows; after it, the selected rows'
                # tokens: the same as decoding the selected rows from the start
                assert torch.allclose(decode(rows, reorder_at), alone, atol=1e-5)
        _, caches = model.start(prefix)
        with pytest.raises(ValueError, match="KV cache full"):
            caches[0].append(*[torch.zeros(3, model.cfg.n_heads, model.pos.shape[0], 4)] * 2)


def test_training_lowers_the_loss(trained):
    _, history, result, _ = trained
    assert history[-1]["val_loss"] < history[0]["val_loss"] - 0.2
    assert history[-1]["train_loss"] < history[0]["train_loss"]
    assert result.best_unit >= 4
    assert [row["unit"] for row in history] == [1, 2, 3, 4, 5]
    assert all(row["val"] == row["val_loss"] for row in history)   # pretraining selects on the loss


@pytest.mark.parametrize("written_by", ["this version", "a version before plad.learn.loop"])
def test_resume_after_a_kill_continues_identically(tmp_path, programs, written_by):
    cfg = dict(batch_size=32, lr=1e-3, steps_per_epoch=5, patience=10)
    val_batch = next(synthetic_batches(programs[:64], batch_size=64)(0))

    def validate(m):
        with torch.no_grad():
            return {"val_loss": float(m.eval().loss(*val_batch)[0])}

    def run(out, epochs, model=None):
        torch.manual_seed(1)
        model = model or PLADNet(tiny_config())
        fit(model, synthetic_batches(programs[:500], 32), validate, TrainConfig(max_epochs=epochs, **cfg), out,
            FitSetup("csg2d", DOMAIN.tokens.names))
        return torch.load(out / "last.pt", weights_only=False)["state_dict"]

    straight = run(tmp_path / "a", 3)
    run(tmp_path / "b", 1)          # "killed" after one epoch
    if written_by != "this version":   # the loop state as the earlier fit() wrote it
        payload = torch.load(tmp_path / "b" / "last.pt", weights_only=False)
        s = payload.pop("loop")
        payload["train_state"] = {"epoch": s["unit"], "best": s["best"], "best_epoch": s["best_unit"],
                                  "bad_epochs": s["since_best"], "seconds": s["seconds"]}
        torch.save(payload, tmp_path / "b" / "last.pt")
    resumed = run(tmp_path / "b", 3)  # the same command again
    for k in straight:
        assert torch.equal(straight[k], resumed[k]), k


def test_checkpoints_of_earlier_versions_load(tmp_path):
    """A checkpoint config as written before Architecture existed (other key order, lists, fewer keys)."""
    torch.manual_seed(0)
    model = PLADNet(tiny_config()).eval()
    old = {"vocab_size": len(DOMAIN.tokens), "max_len": DOMAIN.tokens.max_len, "input_shape": [64, 64],
           "d_model": 32, "n_layers": 1, "n_heads": 2, "dim_ff": 64, "dropout": 0.1, "enc_channels": [4, 8, 8, 16]}
    torch.save({"format": "plad-checkpoint-1", "domain": "csg2d", "tokens": DOMAIN.tokens.names, "config": old,
                "state_dict": model.state_dict()}, tmp_path / "old.pt")
    loaded, _ = load_model(tmp_path / "old.pt")
    assert loaded.cfg == model.cfg
    x = torch.rand(4, 64, 64) > 0.7
    assert greedy_decode(loaded, DOMAIN.tokens, x) == greedy_decode(model, DOMAIN.tokens, x)


def test_one_architecture_dataclass_for_params_and_checkpoints():
    from plad.config import build
    from plad.learn.pretrain import PretrainConfig

    cfg = build(PretrainConfig, {"domain": "csg2d", "model": {"d_model": 32, "n_heads": 2, "enc_channels": [4, 8]}},
                "pretrain")
    net = ModelConfig.for_domain(cfg.model, DOMAIN)
    assert net == tiny_config(n_layers=Architecture().n_layers, dim_ff=Architecture().dim_ff, enc_channels=(4, 8))
    assert set(net.to_dict()) == {f.name for f in dataclasses.fields(ModelConfig)}


def test_checkpoint_rebuilds_the_model_from_the_file_alone(trained, tmp_path):
    model, *_ = trained
    path = save_checkpoint(tmp_path / "m.pt", model, "csg2d", DOMAIN.tokens.names)
    loaded, domain = load_model(path)
    assert domain == "csg2d" and loaded.cfg == model.cfg
    x = torch.rand(4, 64, 64) > 0.7
    assert greedy_decode(loaded, DOMAIN.tokens, x) == greedy_decode(model, DOMAIN.tokens, x)
    with pytest.raises(CheckpointError, match="not a csg3d one|a csg2d model"):
        load_model(path, expect_domain="csg3d")
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="bad.pt"):
        load_model(tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_model(tmp_path / "none.pt")


def synthetic_targets(n=48, seed=5):
    progs = DOMAIN.sample(n, np.random.default_rng(seed))
    return DOMAIN.execute(pad_programs(progs))


def test_beam_one_is_greedy_decoding(trained):
    model, *_ = trained
    targets = synthetic_targets()
    greedy = greedy_decode(model, DOMAIN.tokens, targets)
    result = beam_search(model, DOMAIN.tokens, targets, beam=1)
    assert [result.program(b) for b in range(len(targets))] == greedy


def test_beam_returns_valid_distinct_programs_best_first(trained):
    model, *_ = trained
    targets = synthetic_targets(16)
    result = beam_search(model, DOMAIN.tokens, targets, beam=5)
    assert result.programs.shape[:2] == (16, 5)
    assert (result.logp[:, :-1] >= result.logp[:, 1:]).all()
    for b in range(16):
        progs = [tuple(result.program(b, k)) for k in range(5)]
        assert len(set(progs)) == 5
        for p in progs:
            DOMAIN.check(list(p))


def log_probability(model, shape: torch.Tensor, program: list[int]) -> float:
    """log p(program | shape) under the model by teacher forcing, token by token without the search (the
    network's own softmax over the whole vocabulary, as it is trained; the grammar mask only rules tokens out)."""
    table = DOMAIN.tokens
    tokens = torch.tensor(program)
    tokens_in = torch.cat([torch.tensor([model.cfg.bos]), tokens[:-1]])[None]
    with torch.no_grad():
        logits = model(shape[None], tokens_in)[0].float()                     # (n, V)
    state = table.initial_state(1, logits.device)
    total = 0.0
    for i, token in enumerate(program):
        assert table.mask(state)[0, token]                                   # a token the grammar allows there
        total += float(torch.log_softmax(logits[i], -1)[token])
        state = table.advance(state, tokens[i:i + 1])
    return total


def test_every_beam_width_returns_programs_at_their_exact_log_probability(trained):
    """What beam search guarantees at any width: K distinct valid programs per shape, best log-probability
    first, each scored at its exact log-probability under the model. Not that a wider beam scores better:
    the beams of two widths are not nested (a wider one keeps other prefixes, which may end in programs that
    are less likely or fit the shape worse), so neither the likelihood nor the metric of the best program
    is monotone in the width, shape by shape or on average."""
    model, *_ = trained
    targets = synthetic_targets(6)
    for k in (1, 3, 10):
        result = beam_search(model, DOMAIN.tokens, targets, beam=k)
        assert torch.isfinite(result.logp).all()          # the grammar allows many more than 10 programs
        assert (result.logp[:, :-1] >= result.logp[:, 1:]).all()
        for b in range(len(targets)):
            progs = [result.program(b, j) for j in range(k)]
            assert len({tuple(p) for p in progs}) == k
            for j, prog in enumerate(progs):
                DOMAIN.check(prog)
                assert log_probability(model, targets[b], prog) == pytest.approx(float(result.logp[b, j]), abs=1e-4)


def test_best_of_beam_picks_the_best_candidate_by_the_metric(trained):
    model, *_ = trained
    targets = synthetic_targets(16)
    inferred = infer_programs(model, DOMAIN, targets, beam=4)
    cand = DOMAIN.execute(inferred.beam.programs.view(16 * 4, -1)).view(16, 4, 64, 64)
    values = DOMAIN.metric.score_candidates(cand, targets)
    assert torch.allclose(inferred.values, values.min(1).values.double())
    again = DOMAIN.metric(DOMAIN.execute(pad_programs(inferred.programs)), targets)
    assert torch.allclose(again, inferred.values)


def test_encoder_options_normalization_coordinates_and_kernel():
    """Batch norm, coordinate channels and the kernel size change the encoder, not the interface."""
    torch.manual_seed(0)
    for shape in [(64, 64), (32, 32, 32)]:
        plain = PLADNet(tiny_config(input_shape=shape))
        model = PLADNet(tiny_config(input_shape=shape, enc_norm=True, coord_channels=True, enc_kernel=3))
        assert model.num_visual == plain.num_visual
        first = model.encoder.net[0]
        assert first.in_channels == 1 + len(shape) and first.kernel_size[0] == 3 and first.bias is None
        norms = [m for m in model.encoder.net if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d))]
        assert len(norms) == 4
        # building the model (which probes the encoder's output size) leaves the running statistics alone
        assert all(torch.equal(n.running_mean, torch.zeros_like(n.running_mean)) for n in norms)
        # coordinates are a non-persistent buffer: checkpoints hold weights only
        assert not any("coords" in k for k in model.state_dict())
        # the coordinates make the encoding position-aware: a shape and its shifted copy differ
        x = torch.zeros(2, *shape, dtype=torch.bool)
        x[(0,) + tuple(slice(4, 10) for _ in shape)] = True
        x[(1,) + tuple(slice(20, 26) for _ in shape)] = True
        with torch.no_grad():
            prefix = model.eval().encode(x)
        assert prefix.shape == (2, model.num_visual, model.cfg.d_model)
        assert not torch.allclose(prefix[0], prefix[1])


def test_checkpoint_with_encoder_options_round_trips(tmp_path):
    csg3d = get_domain("csg3d")
    cfg = tiny_config("csg3d", enc_norm=True, coord_channels=True, enc_kernel=3)
    model = PLADNet(cfg)
    model.train()(torch.rand(8, 32, 32, 32) > 0.5, torch.full((8, 1), cfg.bos))  # moves the running statistics
    path = save_checkpoint(tmp_path / "m.pt", model, "csg3d", csg3d.tokens.names)
    loaded, _ = load_model(path)
    assert loaded.cfg == cfg
    x = torch.rand(3, 32, 32, 32) > 0.6
    with torch.no_grad():
        assert torch.allclose(loaded.eval().encode(x), model.eval().encode(x))


@pytest.mark.parametrize("domain", ["csg2d", "csg3d"])
@pytest.mark.parametrize("options", [{}, {"coord_channels": True, "enc_kernel": 3},
                                     {"enc_norm": True, "coord_channels": True}])
def test_fast_encoder_equals_its_definition(domain, options):
    """forward's shortcuts (pool before ReLU, the coordinates' convolution once per batch, channels-last
    first block, batch norm folded into the convolution in evaluation) give the values and gradients of the
    plain definition, in training and evaluation."""
    torch.manual_seed(0)
    model = PLADNet(tiny_config(domain, **options))
    enc = model.encoder
    x = torch.rand(4, *model.cfg.input_shape) > 0.7
    with torch.no_grad():   # batch-norm statistics and affine parameters far from their initial identity
        for m in enc.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-1, 1), m.running_var.uniform_(0.5, 2)
                m.weight.uniform_(0.5, 2), m.bias.uniform_(-1, 1)
    enc.eval()
    with torch.no_grad():
        assert torch.allclose(enc(x), enc.forward_plain(x), atol=1e-5)
    for m in enc.modules():   # training uses batch statistics: back to the initial parameters
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_parameters()
    enc.train()
    grads = []
    for forward in (enc.forward, enc.forward_plain):
        enc.zero_grad()
        torch.manual_seed(1)            # the same channel-dropout draws
        out = forward(x)
        out.square().sum().backward()
        grads.append((out.detach(), [p.grad.clone() for p in enc.parameters()]))
    (fast, g_fast), (plain, g_plain) = grads
    assert torch.allclose(fast, plain, atol=1e-5)
    for a, b in zip(g_fast, g_plain):   # float sums in another order: equal to 1e-4 of the largest entry
        assert (a - b).abs().max() <= 1e-4 * b.abs().max() + 1e-6


def test_prefix_norm_makes_the_visual_tokens_vary_across_shapes():
    """prefix_norm: in training, every feature of the visual prefix has mean 0 and variance 1 over the
    batch, whatever the encoder does; a single shape uses the running statistics, as evaluation does."""
    torch.manual_seed(0)
    model = PLADNet(tiny_config(input_shape=(32, 32, 32), prefix_norm=True, dropout=0.0)).train()
    with torch.no_grad():
        for p in model.encoder.mlp[-1].parameters():
            p.add_(100.0)    # a large shape-independent part, as the ShapeAssembly encoder grew
    x = torch.rand(16, 32, 32, 32) > 0.7
    prefix = model.encode(x)
    assert prefix.mean(0).abs().max() < 1e-3
    assert torch.allclose(prefix.var(0, unbiased=False), torch.ones_like(prefix[0]), atol=1e-3)
    one = model.encode(x[:1])
    model.eval()
    assert torch.allclose(one, model.encode(x[:1]), atol=1e-5)
    assert not torch.allclose(model.encode(x[:1]), model.encode(x[1:2]))
