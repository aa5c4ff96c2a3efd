"""P_BEST with search (plad.learn.pbest_search): seeding and rewriting never make an entry worse, and resume."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plad.config import ConfigError, build
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.methods import MethodConfig, PBestSearchConfig
from plad.learn.pbest import PBest
from plad.learn.pbest_search import PBestSearch, check

SMALL = {"insertions": 3, "refine": {"rounds": 0}}


def _targets(domain, n: int, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return domain.execute(pad_programs(domain.sample(n, rng))).numpy()


def _pbest_of_random_programs(domain, targets: np.ndarray, seed: int = 5) -> PBest:
    """P_BEST filled with random programs (poor entries) for every target."""
    programs = domain.sample(len(targets), np.random.default_rng(seed))
    execs = domain.execute(pad_programs(programs))
    values = domain.metric(execs, torch.from_numpy(targets)).numpy()
    pbest = PBest(len(targets), domain.shape, domain.tokens.max_len, domain.metric)
    pbest.update(np.arange(len(targets)), programs, values, execs.numpy())
    return pbest


def _oriented(domain, v):
    return -v if domain.metric.higher_is_better else v


def test_seeding_improves_pbest_and_never_makes_an_entry_worse(tmp_path):
    domain = get_domain("csg2d")
    targets = _targets(domain, 12)
    pbest = _pbest_of_random_programs(domain, targets)
    before = pbest.values.copy()
    cfg = PBestSearchConfig(seed_share=1.0, seed_config=SMALL, rewrite_share=0.5, rewrite_config={"rounds": 1},
                            chunk=5)
    row = PBestSearch(domain, cfg, tmp_path).after_infer(1, pbest, targets)
    assert not (_oriented(domain, pbest.values) > _oriented(domain, before)).any()   # never worse
    assert np.nanmean(_oriented(domain, pbest.values)) < np.nanmean(_oriented(domain, before))   # better overall
    assert row["seed_shapes"] == 12 and row["seed_improved"] > 0 and row["seed_gain"] > 0
    assert row["rewrite_shapes"] == 6 and row["rewrite_gain"] >= 0 and row["seed_seconds"] > 0
    # every entry's tokens, execution and value agree with the domain's executor and metric
    execs = domain.execute(pad_programs([pbest.program(i) for i in range(len(pbest))]))
    assert torch.equal(execs, torch.from_numpy(pbest.executions))
    assert np.array_equal(domain.metric(execs, torch.from_numpy(targets)).numpy(), pbest.values)
    assert pbest.refined.sum() == 6      # the rewritten entries are marked
    # a later round rewrites entries not yet refined first
    row2 = PBestSearch(domain, cfg, tmp_path).after_infer(2, pbest, targets)
    assert "seed_shapes" not in row2 and pbest.refined.all()


def test_rewriting_is_never_worse_in_3d(tmp_path):
    domain = get_domain("csg3d")
    targets = _targets(domain, 4)
    pbest = _pbest_of_random_programs(domain, targets)
    before = pbest.values.copy()
    cfg = PBestSearchConfig(seed_share=0.0, rewrite_share=1.0, rewrite_config={"rounds": 1, "po_sweeps": 1})
    row = PBestSearch(domain, cfg, tmp_path).after_infer(1, pbest, targets)
    assert not (_oriented(domain, pbest.values) > _oriented(domain, before)).any()
    assert row["rewrite_shapes"] == 4 and pbest.refined.all()


def test_a_killed_seeding_resumes_without_redoing_finished_chunks(tmp_path, monkeypatch):
    import plad.learn.pbest_search as ps

    domain = get_domain("csg2d")
    targets = _targets(domain, 9)
    cfg = PBestSearchConfig(seed_share=1.0, seed_config=SMALL, rewrite_share=0.0, chunk=3)
    real = ps.run_chunks
    searched: list[int] = []

    def dies_after_two(*args, **kwargs):
        for k, r in enumerate(real(*args, **kwargs)):
            if k == 2:
                raise KeyboardInterrupt   # killed while the third chunk's result arrives
            searched.extend(r.index.tolist())
            yield r

    monkeypatch.setattr(ps, "run_chunks", dies_after_two)
    pbest = PBest(len(targets), domain.shape, domain.tokens.max_len, domain.metric)
    with pytest.raises(KeyboardInterrupt):
        PBestSearch(domain, cfg, tmp_path).after_infer(1, pbest, targets)
    assert len(sorted((tmp_path / "search" / "seed").glob("chunk_*.npz"))) == 2
    assert len(searched) == 6

    searched.clear()
    monkeypatch.setattr(ps, "run_chunks", lambda *a, **k: (searched.extend(r.index.tolist()) or r
                                                           for r in real(*a, **k)))
    pbest = PBest(len(targets), domain.shape, domain.tokens.max_len, domain.metric)
    row = PBestSearch(domain, cfg, tmp_path).after_infer(1, pbest, targets)
    assert len(searched) == 3                      # only the unfinished chunk is searched again
    assert row["seed_chunks_resumed"] == 2 and pbest.has.all()
    # the same P_BEST as an uninterrupted seeding
    fresh = PBest(len(targets), domain.shape, domain.tokens.max_len, domain.metric)
    PBestSearch(domain, cfg, tmp_path / "again").after_infer(1, fresh, targets)
    assert np.array_equal(fresh.values, pbest.values) and np.array_equal(fresh.programs, pbest.programs)


def test_two_worker_processes_give_the_same_programs(tmp_path):
    domain = get_domain("csg2d")
    targets = _targets(domain, 6)
    pbests = []
    for workers in (1, 2):
        cfg = PBestSearchConfig(seed_share=1.0, seed_config=SMALL, rewrite_share=0.0, chunk=3, workers=workers)
        pbest = PBest(len(targets), domain.shape, domain.tokens.max_len, domain.metric)
        PBestSearch(domain, cfg, tmp_path / str(workers)).after_infer(1, pbest, targets)
        pbests.append(pbest)
    assert np.array_equal(pbests[0].programs, pbests[1].programs)


def test_the_search_block_is_typed_and_checked():
    m = build(MethodConfig, {"method": "lest+st+ws", "search": {"seed_share": 0.5, "chunk": 8}}, "m")
    assert isinstance(m.search, PBestSearchConfig) and m.search.chunk == 8
    assert build(MethodConfig, {"method": "lest+st"}, "m").search is None
    with pytest.raises(ConfigError, match="seed_sahre"):
        build(MethodConfig, {"search": {"seed_sahre": 0.5}}, "m")
    domain = get_domain("csg2d")
    with pytest.raises(ConfigError, match="seed_share"):
        check(PBestSearchConfig(seed_share=1.5), domain, "x")
    with pytest.raises(ConfigError, match="rewrite_config"):
        check(PBestSearchConfig(rewrite_config={"roundz": 1}), domain, "x")
    with pytest.raises(ConfigError, match="seed_config"):
        check(PBestSearchConfig(seed_config={"insertionz": 1}), domain, "x")


def test_rounds_with_search_seed_then_rewrite_and_log_it_in_the_history(tmp_path):
    import json

    from plad.learn.job import Job
    from plad.learn.rounds import RoundHooks, RoundsConfig, run_rounds
    from plad.learn.train import TrainConfig
    from plad.model.network import ModelConfig, PLADNet

    domain = get_domain("csg2d")
    shapes = _targets(domain, 20, seed=11)
    cfg = RoundsConfig(infer_beam=2, infer_batch=20, val_beam_epoch=1, val_beam_round=1, max_rounds=2,
                       round_patience=100, train=TrainConfig(batch_size=8, steps_per_epoch=2, max_epochs=1))
    search = PBestSearchConfig(seed_share=1.0, seed_config=SMALL, rewrite_share=0.5, rewrite_config={"rounds": 1},
                               chunk=8)
    means = {}
    for name, hooks in (("plain", None), ("search", "yes")):
        torch.manual_seed(0)
        model = PLADNet(ModelConfig(vocab_size=len(domain.tokens), max_len=domain.tokens.max_len,
                                    input_shape=domain.shape, d_model=16, n_layers=1, n_heads=2, dim_ff=32,
                                    enc_channels=(4, 4, 8, 8)))
        out = tmp_path / name
        job = Job(model, domain, shapes[:16], shapes[16:], out)
        if hooks:
            hooks = RoundHooks(after_infer=PBestSearch(domain, search, out).after_infer)
        run_rounds(job, MethodConfig("lest+st"), cfg, hooks)
        history = json.loads((out / "state.json").read_text())["history"]
        means[name] = history[1]["pbest_mean"]
        if name == "search":
            assert history[1]["seed_shapes"] == 16 and "seed_shapes" not in history[2]
            assert history[1]["rewrite_shapes"] == history[2]["rewrite_shapes"] == 8
            assert all(history[r]["rewrite_seconds"] > 0 for r in (1, 2))
            # no time limit: no step was cut short, and the run's work is what the config fixed
            assert all(history[r]["seed_stopped_by_time"] == 0.0 for r in (1,))
            assert not any(history[r].get("stopped_by_time") for r in (1, 2))
            pbest = PBest.load(out / "pbest.npz", domain.metric)
            assert pbest.refined.sum() >= 8   # the flags are saved with P_BEST
    assert means["search"] < means["plain"]   # Chamfer: the seeded P_BEST is better than inference alone


def test_a_killed_rewrite_resumes_with_the_same_plan_and_finished_chunks(tmp_path, monkeypatch):
    import plad.learn.pbest_search as ps

    domain = get_domain("csg2d")
    targets = _targets(domain, 8)
    cfg = PBestSearchConfig(seed_share=0.0, rewrite_share=0.5, rewrite_config={"rounds": 1, "po_sweeps": 1},
                            chunk=2)
    real = ps.run_chunks
    done: list[int] = []

    def dies_after_one(*args, **kwargs):
        for k, r in enumerate(real(*args, **kwargs)):
            if k == 1:
                raise KeyboardInterrupt
            done.extend(r.index.tolist())
            yield r

    monkeypatch.setattr(ps, "run_chunks", dies_after_one)
    pbest = _pbest_of_random_programs(domain, targets)
    with pytest.raises(KeyboardInterrupt):
        PBestSearch(domain, cfg, tmp_path).after_infer(3, pbest, targets)
    planned = np.load(tmp_path / "search" / "rewrite_003" / "plan.npz")["index"]
    assert len(planned) == 4 and set(done) < set(planned.tolist())
    monkeypatch.setattr(ps, "run_chunks", real)
    pbest = _pbest_of_random_programs(domain, targets)
    pbest.refined[planned[:2]] = True     # another choice would now be made: the plan on disk wins
    row = PBestSearch(domain, cfg, tmp_path).after_infer(3, pbest, targets)
    assert row["rewrite_chunks_resumed"] == 1 and row["rewrite_shapes"] == 4
    assert set(np.nonzero(pbest.refined)[0].tolist()) == set(planned.tolist())


def test_the_configured_time_limit_holds_in_the_pool():
    from plad.rewrite.pool import refine_all

    domain = get_domain("csg2d")
    targets = _targets(domain, 4)
    programs = domain.sample(4, np.random.default_rng(9))
    same, _, _, timed = refine_all("csg2d", programs, targets, {"time_limit": 1e-9})   # over at once: no step
    assert same == [list(p) for p in programs] and timed   # ... and the result says a time limit shaped it
    better, values, _, timed = refine_all("csg2d", programs, targets, {"rounds": 1})
    assert better != same and not timed
