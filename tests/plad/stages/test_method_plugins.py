"""Fine-tuning methods are plugins (plad.learn.method_registry): the contract every registered method and source
keeps, and a method added from this test suite alone (its module, its params, its test) that runs through the
real stage, the report's table and the paper profile without a line of plad/ naming it."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
import yaml

from plad.config import load_params, section
from plad.domains.base import pad_programs
from plad.eval.report import from_files, label, table_markdown
from plad.layout import BEST, STATE, Layout
from plad.learn import method_registry as registry
from plad.learn.finetune import FinetuneStageConfig, plan
from plad.learn.loop import JsonStore, Limits, Loop, Unit, read_state
from plad.learn.method_registry import Method, PairSource
from plad.learn.methods import MethodConfig
from plad.learn.rl import RLConfig
from plad.learn.rounds import RoundsConfig, mean_metric
from plad.learn.train import TrainConfig
from plad.learn.ws import ws_source
from plad.model.checkpoint import read_checkpoint, save_checkpoint
from plad.stages.finetune import finetune_stage
from tests.conftest import REPO_ROOT
from tests.tiny import csg2d_inputs, tiny_checkpoint

pytestmark = pytest.mark.unit


# -- the toy plugins: the example source (a replay of synthetic pairs) and a method of its own step --
def synthetic_pairs(domain, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` synthetic programs of the domain (-1 padded, int16) and their executions."""
    programs = domain.sample(n, np.random.default_rng(seed))
    tokens = pad_programs(programs, pad=-1)
    executions = domain.execute(tokens.clamp(min=0)).numpy()
    return tokens.numpy().astype(np.int16), executions


class SyntheticReplay(PairSource):
    """``syn``: synthetic (execution, program) pairs, new ones each round, beside P_BEST's sources."""

    def build(self, ctx):
        programs, executions = synthetic_pairs(ctx.job.domain, 32, ctx.job.seed * 1_000 + ctx.rnd)
        return ws_source(programs, executions, ctx.device), {"syn_pairs": float(len(programs))}


class SyntheticSteps(Method):
    """``toy``: its own training step, plain maximum likelihood on synthetic pairs, one epoch per unit, selected
    on the validation shapes like every method (the loop of plad.learn.loop)."""

    checkpoint = "toy.pt"

    def check(self, spec, cfg, where: str) -> None:
        super().check(spec, cfg, where)
        if spec.search is not None:
            raise ValueError(f"{where}.search: the toy method has no P_BEST")

    def run(self, job, spec, cfg, hooks) -> dict:
        model, domain, out, train = job.model, job.domain, job.out_dir, cfg.plad.train
        opt = torch.optim.Adam(model.parameters(), lr=train.lr)
        names = domain.tokens.names

        def validate() -> float:
            return mean_metric(model, domain, job.val, cfg.plad.val_beam_round, cfg.plad.infer_batch)

        def epoch(unit: int, remaining) -> Unit:
            programs, shapes = synthetic_pairs(domain, 64, job.seed * 1_000 + unit)
            draw, rng, total = ws_source(programs, shapes, torch.device("cpu")), np.random.default_rng(unit), 0.0
            model.train()
            for _ in range(train.steps_per_epoch):
                loss, _ = model.loss(*draw(rng, train.batch_size))
                opt.zero_grad()
                loss.backward()
                opt.step()
                total += float(loss.detach()) / train.steps_per_epoch
            model.eval()
            return Unit(validate(), {"train_loss": total})

        def save(unit: int, folder) -> None:
            save_checkpoint(folder / self.checkpoint, model, domain.name, names, {"optimizer": opt.state_dict()})

        def restore() -> None:
            payload = read_checkpoint(out / self.checkpoint)
            model.load_state_dict(payload["state_dict"])
            opt.load_state_dict(payload["optimizer"])

        def keep_best(unit: int, value: float) -> None:
            save_checkpoint(out / BEST, model, domain.name, names, {"unit": unit, "val": value})

        limits = Limits(self.rounds(spec, cfg).max_rounds, 1000, 0.0, job.budget_seconds)
        result = Loop("epoch", domain.metric, limits, JsonStore(out / STATE, save=save, restore=restore)).run(
            epoch, start=validate, keep_best=keep_best,
            restore_best=lambda: model.load_state_dict(read_checkpoint(out / BEST)["state_dict"]),
            on_unit=hooks.on_unit)
        return {"method": "toy", **result.summary()}


@pytest.fixture
def toy_plugins():
    """The toy method and source, registered from outside plad/ for one test, then forgotten."""
    registry.register_source("syn", SyntheticReplay(), label="SYN")
    registry.register_method("toy", SyntheticSteps(), label="Toy (synthetic steps)")
    yield
    registry.unregister("toy")
    registry.unregister("syn")


@pytest.fixture(scope="module")
def layout(tmp_path_factory, datasets_dir):
    root = csg2d_inputs(tmp_path_factory.mktemp("plugins"), datasets_dir)
    tiny_checkpoint(Layout(root).model("csg2d", "sp"), "csg2d")
    return Layout(root)


def tiny(methods: dict[str, MethodConfig], key: str) -> FinetuneStageConfig:
    plad = RoundsConfig(infer_beam=1, infer_batch=8, val_beam_epoch=1, val_beam_round=1, max_rounds=2,
                        train=TrainConfig(batch_size=4, steps_per_epoch=2, max_epochs=1))
    return FinetuneStageConfig(domain="csg2d", key=key, device="cpu", threads=1, train_limit=8, val_limit=4,
                               plad=plad, rl=RLConfig(batch_size=4, steps_per_epoch=2, max_epochs=2, val_beam=1),
                               methods=methods)


# -- the contract ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", [*registry.method_names(), registry.MIXTURE])
def test_every_method_declares_its_label_checkpoint_and_steps(name):
    method = registry.get_method(name if name != registry.MIXTURE else "lest+st")
    assert isinstance(method, Method)
    assert type(method).run is not Method.run   # a training step of its own (the mixtures': the PLAD rounds)
    assert method.checkpoint.endswith(".pt") and method.checkpoint != BEST
    if name != registry.MIXTURE:
        assert registry.key_label(name) and label(name) == registry.key_label(name)


@pytest.mark.parametrize("name", registry.source_names())
def test_every_source_builds_its_draw_and_labels_its_mixtures(name):
    assert isinstance(registry.get_source(name), PairSource)
    assert type(registry.get_source(name)).build is not PairSource.build
    assert str(registry.parse_mixture(f"{name}:2")) == name
    assert label(name) == registry.key_label(name) and label(f"{name}_per_round").endswith(" (per-round)")


def test_every_method_of_params_is_registered_and_labelled_by_the_registry():
    params = load_params(REPO_ROOT / "params.yaml")
    for key, entry in params["finetune"]["csg2d"]["methods"].items():
        registry.get_method(entry["method"])   # raises for a method no plugin declares
        assert registry.key_label(key) == label(key)


@pytest.mark.parametrize("key, method", [("rl", "rl"), ("lest_st_ws", "lest+st+ws")])
def test_every_builtin_method_runs_through_the_stage(layout, key, method):
    summary = finetune_stage(tiny({key: MethodConfig(method=method)}, key), layout)
    out = layout.finetune_dir("csg2d", key)
    run = plan(tiny({key: MethodConfig(method=method)}, key))
    assert (out / run.method.checkpoint).exists() and (out / BEST).exists()
    assert summary["method"] == method and set(run.method.work(run.spec, run.cfg)) <= set(summary)
    assert len(read_state(out / STATE).history) == summary["units"] + 1


# -- a method added from the test suite alone ---------------------------------------------------------------
def test_a_method_and_a_source_registered_outside_plad_run_through_stage_report_and_paper_profile(
        toy_plugins, layout, tmp_path):
    methods = {"toy": MethodConfig(method="toy"), "lest_st_syn": MethodConfig(method="lest+st+syn")}
    toy = finetune_stage(tiny(methods, "toy"), layout)
    mixed = finetune_stage(tiny(methods, "lest_st_syn"), layout)
    assert toy["method"] == "toy" and toy["max_rounds"] == 2 and toy["units"] == 2
    assert (layout.finetune_dir("csg2d", "toy") / "toy.pt").exists()
    assert mixed["method"] == "lest+st+syn" and mixed["units"] == 2
    rows = read_state(layout.finetune_dir("csg2d", "lest_st_syn") / STATE).history[1:]
    assert [r["syn_pairs"] for r in rows] == [32.0, 32.0]   # the source's own columns reach the round's history
    # the report: the rows carry the labels the plugins declared, with their training columns
    table = table_markdown({"csg2d": from_files("csg2d", ["sp", "toy", "lest_st_syn"], layout)},
                           ["sp", "toy", "lest_st_syn"], {})
    assert "| Toy (synthetic steps) |" in table and "| LEST+ST+SYN |" in table
    # the paper profile: its params entry is all the method needs (no line in profiles/paper.yaml)
    data = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    data["methods"].append("toy")
    data["finetune"]["base"]["methods"]["toy"] = {"method": "toy", "max_rounds": 3}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    shutil.copytree(REPO_ROOT / "profiles", tmp_path / "profiles")
    for profile, rounds in (("cpu", 3), ("paper", None)):
        cfg = section(load_params(tmp_path / "params.yaml", profile=profile), "finetune.csg2d", FinetuneStageConfig)
        cfg.key = "toy"
        run = plan(cfg)
        assert run.spec.max_rounds == rounds and run.method is registry.get_method("toy")
        assert run.method.work(run.spec, cfg)["max_rounds"] == (rounds or cfg.plad.max_rounds)
