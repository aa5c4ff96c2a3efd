"""Issue 14: program complexity, the curriculum sampler with replay, the prefix-swap gap, the new model knobs."""
import dataclasses

import numpy as np
import pytest
import torch
import yaml

from plad.config import load_params
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn import distributed as dist
from plad.learn.curriculum import Curriculum, CurriculumConfig, pool
from plad.learn.diagnostics import prefix_gap
from plad.learn.train import FitSetup, TrainConfig, fit
from plad.model.network import ModelConfig, PLADNet
from plad.stages.synthesize import to_array
from tests.conftest import REPO_ROOT as REPO

CSG2D = get_domain("csg2d")


def tiny(domain=CSG2D, **kw) -> PLADNet:
    base = dict(vocab_size=len(domain.tokens), max_len=domain.tokens.max_len, input_shape=domain.shape,
                d_model=32, n_layers=1, n_heads=2, dim_ff=64, enc_channels=(4, 8, 8, 16), dropout=0.0)
    return PLADNet(ModelConfig(**{**base, **kw}))


# -- complexity ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text, expected", [
    ("csg3d", "diff cuboid 16 16 16 20 20 20 ellipsoid 16 16 16 12 12 30", 2),
    ("csg3d", "union cuboid 16 16 16 2 2 2 union cuboid 1 1 1 3 3 3 ellipsoid 9 9 9 4 4 4", 3),
])
def test_complexity_counts_primitives(name, text, expected):
    domain = get_domain(name)
    ids = domain.parse(text)
    assert domain.complexity(to_array([ids, ids[:0] + domain.parse("cuboid 1 1 1 2 2 2")], 100)).tolist() == \
        [expected, 1]


@pytest.mark.parametrize("name, lo, hi", [("csg2d", 1, 7), ("csg3d", 2, 12), ("shapeassembly", 2, 8)])
def test_complexity_is_the_samplers_stratum(name, lo, hi):
    """Every domain's sampler is uniform over its strata: the complexities cover exactly that range."""
    domain = get_domain(name)
    c = domain.complexity(to_array(domain.sample(60, np.random.default_rng(1)), domain.tokens.max_len))
    assert c.min() >= lo and c.max() <= hi and len(set(c.tolist())) >= (hi - lo + 1) // 2


def test_synthesize_records_the_complexity(tmp_path):
    from plad.layout import Layout
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    summary = synthesize(SynthesizeConfig(domain="csg2d", train_programs=50, val_programs=10), Layout(tmp_path))
    with np.load(Layout(tmp_path).synthetic("csg2d")) as z:
        assert z["train_complexity"].tolist() == CSG2D.complexity(z["train"]).tolist()
        assert len(z["val_complexity"]) == 10
    assert sum(summary["train_complexity"].values()) == 50


# -- the curriculum --------------------------------------------------------------------------------
def complexities(n=4000, seed=0):
    return np.random.default_rng(seed).integers(2, 13, n)   # as csg3d: 2..12, uniform


@pytest.mark.parametrize("stage, max_c", [(0, 2), (1, 4), (2, 8), (3, 12)])
def test_the_sampler_gives_the_requested_mix(stage, max_c):
    c = complexities()
    cur = Curriculum(CurriculumConfig(enabled=True, stages=[2, 4, 8], stage_steps=10, replay=0.25), c, c)
    cur.stage = stage
    it = cur.indices(epoch=3, seed=0, batch_size=64)
    picks = np.concatenate([next(it) for _ in range(200)])
    got = c[picks]
    assert got.max() == max_c and got.min() == 2
    # replay: a quarter of every batch from the easiest programs (complexity 2), the rest uniform over the
    # stage's programs, which holds its own share of easy ones
    stage_share = np.mean(c[pool(c, None if stage == 3 else max_c)] == 2)
    expected = 0.25 + 0.75 * stage_share
    assert abs(np.mean(got == 2) - expected) < 0.02
    for k in range(3, max_c + 1):   # the harder complexities: uniform over the rest
        assert abs(np.mean(got == k) - 0.75 * np.mean(c[pool(c, max_c)] == k)) < 0.02


def test_a_stage_below_the_smallest_complexity_takes_the_smallest():
    c = complexities()
    cur = Curriculum(CurriculumConfig(enabled=True, stages=[1, 4], stage_steps=10, replay=0.0), c, c)
    assert set(c[next(cur.indices(0, 0, 256))].tolist()) == {2}


def test_ranks_draw_disjoint_parts_of_one_global_batch(monkeypatch):
    """Under DDP every rank draws the same global batch and keeps its own part: nothing per rank to save."""
    c = complexities()
    cfg = CurriculumConfig(enabled=True, stages=[4], stage_steps=10, replay=0.5)
    parts = []
    for r in range(2):
        monkeypatch.setattr(dist, "world", lambda: 2)
        monkeypatch.setattr(dist, "rank", lambda r=r: r)
        it = Curriculum(cfg, c, c).indices(epoch=1, seed=7, batch_size=8)
        parts.append([next(it) for _ in range(3)])
    monkeypatch.setattr(dist, "world", lambda: 1)
    monkeypatch.setattr(dist, "rank", lambda: 0)
    single = Curriculum(cfg, c, c).indices(epoch=1, seed=7, batch_size=16)
    for step in range(3):
        both = np.concatenate([parts[0][step], parts[1][step]])
        assert len(parts[0][step]) == 8
        # the same programs as one process with the global batch (replay share counted over the global batch)
        assert both.tolist() == next(single).tolist()


def test_stages_advance_by_steps_gap_accuracy_or_patience_and_round_trip():
    c = complexities()
    cur = Curriculum(CurriculumConfig(enabled=True, stages=[2, 4], stage_steps=100, advance_gap=0.2), c, c)
    cur.end_epoch(50, {"prefix_gap": 0.1, "stage_val_loss": 1.0})
    assert cur.stage == 0
    cur.end_epoch(50, {"prefix_gap": 0.1, "stage_val_loss": 1.0})    # 100 steps
    assert cur.stage == 1 and cur.stage_steps == 0
    cur.end_epoch(10, {"prefix_gap": 0.25, "stage_prefix_gap": 0.1, "stage_val_loss": 1.0})
    assert cur.stage == 1   # the stage's own gap decides
    cur.end_epoch(10, {"prefix_gap": 0.1, "stage_prefix_gap": 0.25, "stage_val_loss": 1.0})   # the gap threshold
    assert cur.stage == 2 and cur.final and cur.max_complexity is None
    row = cur.end_epoch(1000, {"prefix_gap": 0.0})
    assert cur.stage == 2 and row == {"curriculum_stage": 2.0}       # the final stage lasts
    patient = Curriculum(CurriculumConfig(enabled=True, stages=[2], stage_patience=2, advance_acc=0.9), c, c)
    for loss in (1.0, 1.0):
        patient.end_epoch(1, {"stage_val_loss": loss, "stage_val_acc": 0.5})
    assert patient.stage == 0
    patient.end_epoch(1, {"stage_val_loss": 1.0, "stage_val_acc": 0.5})   # two epochs without improving
    assert patient.stage == 1
    again = Curriculum(patient.cfg, c, c)
    again.load_state_dict(cur.state_dict())
    assert again.stage == 2 and again.final


def test_curriculum_config_errors():
    with pytest.raises(ValueError, match="replay"):
        CurriculumConfig(replay=1.0)
    with pytest.raises(ValueError, match="no rule ends a stage"):
        CurriculumConfig(enabled=True, stages=[2])
    with pytest.raises(ValueError, match="increasing"):
        CurriculumConfig(stages=[4, 2])


# -- the prefix-swap gap ---------------------------------------------------------------------------
def few_shapes_batches(n_programs=6, seed=0, batch_size=32, shuffled=False):
    """Batches drawn from a few distinct 1-primitive 2D programs: the program is decided by the shape alone."""
    from plad.domains.csg2d.sampler import sample_programs

    programs = pad_programs(sample_programs(CSG2D.executor, n_programs, np.random.default_rng(seed),
                                            max_primitives=1), pad=-1).clamp(min=0)
    lengths = torch.full((n_programs,), programs.shape[1])
    shapes = CSG2D.execute(programs)

    def batches(epoch):
        gen = torch.Generator().manual_seed(epoch)
        while True:
            i = torch.randint(0, n_programs, (batch_size,), generator=gen)
            j = torch.randint(0, n_programs, (batch_size,), generator=gen) if shuffled else i
            yield shapes[j], programs[i], lengths[i]
    return batches


def test_the_gap_is_zero_for_a_model_that_ignores_its_input_and_positive_once_it_reads_it(tmp_path):
    torch.manual_seed(0)
    val = next(few_shapes_batches(batch_size=64)(100))
    model = tiny(prefix_bos=True)
    # an input-ignoring network: the encoder's last layer outputs its bias only, the same prefix for every shape
    with torch.no_grad():
        model.encoder.mlp[-1].weight.zero_()
    assert abs(prefix_gap(model, *val)) < 1e-6
    # a network that uses its input: a tiny one trained a little on shapes that decide the program
    gaps = {}

    @torch.no_grad()
    def validate(m):
        return {"val_loss": float(m.eval().loss(*val)[0])}

    for shuffled in (False, True):
        torch.manual_seed(0)
        model = tiny(enc_init="kaiming", prefix_bos=True)
        untrained = prefix_gap(model, *val)
        fit(model, few_shapes_batches(shuffled=shuffled), validate,
            TrainConfig(batch_size=32, lr=3e-3, steps_per_epoch=40, max_epochs=2, warmup_steps=10),
            tmp_path / str(shuffled), FitSetup("csg2d", CSG2D.tokens.names))
        gaps[shuffled] = prefix_gap(model, *val)
    # a network that uses its input (trained on shapes that decide the program) pays for another shape's
    # prefix; the same network trained on shuffled (shape, program) pairs learns to ignore its input
    assert gaps[False] > 0.2 and gaps[False] > 10 * abs(untrained), (gaps, untrained)
    assert abs(gaps[True]) < 0.02, gaps


# -- the model knobs -------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(64, 64), (32, 32, 32)])
def test_prefix_bos_decodes_incrementally_as_it_trains(shape):
    torch.manual_seed(0)
    model = tiny(input_shape=shape, prefix_bos=True, enc_init="kaiming").eval()
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
        # the first token's distribution depends on the shape through BOS even without attention to the prefix
        assert not torch.allclose(model._bos(model.encode(x))[0], model._bos(model.encode(x))[1])
    assert torch.allclose(full, torch.stack(steps, 1), atol=1e-5)


def test_kaiming_keeps_the_encoder_signal():
    """Torch's default conv init shrinks the activations block by block; He init keeps them."""
    torch.manual_seed(0)
    x = torch.rand(8, 32, 32, 32) > 0.7
    spread = {}
    for init in ("default", "kaiming"):
        enc = tiny(input_shape=(32, 32, 32), enc_init=init).encoder.eval()
        with torch.no_grad():
            feats = enc.net(x.float().unsqueeze(1))
        spread[init] = float(feats.std())
    assert spread["kaiming"] > 3 * spread["default"]


def test_a_checkpoint_config_without_the_new_keys_builds_the_old_network(tmp_path):
    from plad.model.checkpoint import load_model, save_checkpoint

    old = tiny()
    path = tmp_path / "old.pt"
    save_checkpoint(path, old, "csg2d", CSG2D.tokens.names)
    payload = torch.load(path, weights_only=False)
    for key in ("enc_init", "prefix_bos"):
        del payload["config"][key]
    torch.save(payload, path)
    model, _ = load_model(path, expect_domain="csg2d")
    assert model.bos_proj is None and not model.cfg.prefix_bos and model.cfg.enc_init == "default"
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), old.state_dict().values()))


# -- params and plots ------------------------------------------------------------------------------
def test_the_cpu_profile_has_the_curriculum_for_the_3d_domains_and_paper_the_plain_schedule():
    """The 3D domains pretrain with the curriculum, He init, the input-conditioned BOS and warm-up in the cpu
    (and smoke) profile; 2D keeps the plain schedule, measured better there (docs/results-history.md),
    and so does every domain in the paper profile."""
    from plad.config import section
    from plad.learn.pretrain import PretrainConfig

    for profile, on_3d in (("cpu", True), ("smoke", True), ("paper", False)):
        params = load_params(REPO / "params.yaml", profile=profile)
        for d in params["domains"]:
            on = on_3d and d != "csg2d"
            cfg = section(params, f"pretrain.{d}", PretrainConfig)
            assert cfg.curriculum.enabled is on, (profile, d)
            assert (cfg.model.prefix_bos, cfg.model.enc_init != "default", cfg.train.warmup_steps > 0) == \
                (on, on, on), (profile, d)
            if on:   # every stage has programs below its maximum, and it is below the domain's largest
                assert cfg.curriculum.stages[0] <= 2


def test_dvc_plots_show_the_diagnostic_of_every_domain():
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    ys: dict[str, set[str]] = {}
    for plot in dvc["plots"]:
        for body in plot.values():
            for f, cols in body["y"].items():
                ys.setdefault(f, set()).update([cols] if isinstance(cols, str) else cols)
    for d in params["domains"]:
        metric = get_domain(d).metric.name
        assert {"prefix_gap", f"real_val_{metric}"} <= ys[f"runs/pretrain/{d}/history.csv"], d


def test_pretrain_config_has_the_curriculum_section():
    from plad.learn.pretrain import PretrainConfig

    assert {f.name for f in dataclasses.fields(PretrainConfig)} >= {"curriculum", "gap_programs", "real_val_shapes"}


# -- the stage: pretraining with the curriculum, killed and resumed -----------------------------------
def test_pretraining_with_the_curriculum_resumes_in_its_stage(tmp_path):
    """The stage is checkpointed: a run stopped after epoch 2 and started again equals an uninterrupted one."""
    from plad.layout import HISTORY, LAST, Layout
    from plad.learn.pretrain import PretrainConfig, pretrain
    from plad.model.network import Architecture
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    synthesize(SynthesizeConfig(domain="csg2d", train_programs=300, val_programs=16), Layout(tmp_path / "a"))
    (tmp_path / "b" / "data").mkdir(parents=True)
    (tmp_path / "b" / "data" / "synthetic").symlink_to(tmp_path / "a" / "data" / "synthetic")

    def cfg(epochs):
        return PretrainConfig(
            domain="csg2d", device="cpu", val_metric_shapes=4, gap_programs=8,
            model=Architecture(d_model=16, n_layers=1, n_heads=2, dim_ff=32, enc_channels=(4, 4, 8, 8),
                               prefix_bos=True, enc_init="kaiming"),
            train=TrainConfig(batch_size=8, steps_per_epoch=3, max_epochs=epochs, warmup_steps=4),
            curriculum=CurriculumConfig(enabled=True, stages=[1, 3], stage_steps=6, replay=0.25))

    pretrain(cfg(4), Layout(tmp_path / "a"))
    pretrain(cfg(2), Layout(tmp_path / "b"))
    assert torch.load(tmp_path / "b/runs/pretrain/csg2d" / LAST, weights_only=False)["stages"]["stage"] == 1
    pretrain(cfg(4), Layout(tmp_path / "b"))
    rows = [(tmp_path / r / "runs/pretrain/csg2d" / HISTORY).read_text().splitlines() for r in "ab"]
    strip = lambda line: line.rsplit(",", 1)[0]  # noqa: E731 (without epoch_seconds)
    assert [strip(x) for x in rows[0]] == [strip(x) for x in rows[1]]
    header = rows[0][0].split(",")
    stage = [float(r.split(",")[header.index("curriculum_stage")]) for r in rows[0][1:]]
    assert stage == [0.0, 0.0, 1.0, 1.0]   # the stage each epoch trained in: two epochs of 3 steps per stage
    assert {"prefix_gap", "stage_prefix_gap", "stage_val_loss", "stage_val_acc", "val_chamfer"} <= set(header)
    a, b = (torch.load(tmp_path / r / "runs/pretrain/csg2d" / LAST, weights_only=False)["state_dict"] for r in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)
