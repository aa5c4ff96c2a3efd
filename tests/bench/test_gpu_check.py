"""bench.gpu_check: the paper profile's parts run and report; the whole CPU check is a `slow` test (14 minutes on
the 2-core machine would not fit CI's), the CUDA runs skip without a GPU."""
from __future__ import annotations

import json
import math

import pytest
import torch

from bench import gpu_check
from tests.conftest import REPO_ROOT

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def run(capsys, *args: str) -> tuple[int, list[str]]:
    status = gpu_check.main(["--params", str(REPO_ROOT / "params.yaml"), "--root", str(REPO_ROOT), *args])
    return status, capsys.readouterr().out.strip().splitlines()


def test_beam_search_at_the_paper_size_on_the_cpu(capsys, tmp_path):
    status, lines = run(capsys, "--device", "cpu", "--quick", "--domains", "csg2d", "--parts", "beam10",
                        "--threads", "1", "--json", str(tmp_path / "check.json"))
    assert status == 0 and lines[-1] == "paper profile: 1 parts ok on cpu"
    assert any(line.startswith("csg2d: 7,197,612 parameters (width 256, 8 layers, 16 heads") for line in lines)
    report = json.loads((tmp_path / "check.json").read_text())
    (beam,) = report["results"]
    assert beam["part"] == "beam10" and beam["ok"] and beam["items"] == 2 and beam["rate"] > 0
    assert beam["peak_bytes"] > 0 and report["device"] == "cpu" and report["quick"]
    # 3,000 test shapes in data/prepared/csg2d.json: the estimate is their count over the measured rate
    (estimate,) = report["estimates"]
    per_cpu = beam["items"] / beam["cpu_seconds"]
    assert estimate.endswith(f"evaluate 3,000 test shapes at beam 10: {gpu_check.figure(3000 / per_cpu / 3600)} h")


def test_the_estimates_are_the_profiles_sizes_over_the_measured_rates():
    from plad.config import load_params, section
    from plad.learn.pretrain import PretrainConfig
    from plad.stages.finetune import FinetuneStageConfig
    from plad.stages.synthesize import SynthesizeConfig

    params = load_params(REPO_ROOT / "params.yaml", profile="paper")
    pre = section(params, "pretrain.csg3d", PretrainConfig)
    ft = section(params, "finetune.csg3d", FinetuneStageConfig)
    syn = section(params, "synthesize.csg3d", SynthesizeConfig)
    pretrain = gpu_check.Result("csg3d", "pretrain", ok=True, items=800, seconds=2.0, cpu_seconds=4.0,
                                values={"sample_rate": 1000.0, "sample_rate_cpu": 500.0, "sustained": 400.0,
                                        "sustained_cpu": 200.0})
    rnd = gpu_check.Result("csg3d", "round", ok=True, items=100, seconds=10.0,
                           values={"infer_rate": 10.0, "infer_rate_cpu": 5.0})
    st = gpu_check.Result("csg3d", "st", ok=True, items=300, seconds=1.0)
    lest = gpu_check.Result("csg3d", "lest", ok=True, items=100, seconds=1.0)
    counts = {"train": 3600, "val": 360, "test": 36}
    sizes = gpu_check.sizes_for(pre, ft, None, quick=True)
    lines = gpu_check.estimates("csg3d", {"pretrain": pretrain, "round": rnd, "st": st, "lest": lest}, pre, ft, syn,
                                counts, sizes, per_cpu=False)
    # 2 M programs at 1,000/s; epochs of 1,000 steps of 400 at 400 shapes/s; the paper's 80 M shapes
    assert lines[0] == "csg3d         synthesize 2,000,000 programs: 0.556 h in one process"
    assert lines[1] == ("csg3d         pretrain at 400 shapes/s (batch 8): an epoch of 400,000 shapes 0.278 h; the "
                        "paper's 80 M shapes to convergence 55.6 h")
    # inference 3,600 shapes at 10/s: 0.1 h; an epoch of 100 x 100 at 200 shapes/s: 1/72 h; its validation 0.01 h
    want = 0.1 + 11 * (1 / 72 + 0.01)
    assert lines[2].startswith("csg3d         finetune, a PLAD round: inference over 3,600 shapes at beam 5 0.100 h; "
                               "a training epoch (100 steps of 100) 0.0139 h and its validation on 360 shapes 0.0100 h")
    assert f"a round of 11 epochs (the least patience 10 allows) {gpu_check.figure(want)} h" in lines[2]
    per_cpu = gpu_check.estimates("csg3d", {"pretrain": pretrain}, pre, ft, syn, counts, sizes, per_cpu=True)
    assert "pretrain at 200 shapes/s" in per_cpu[1] and "1.11 h in one process" in per_cpu[0]


def test_figures_keep_three_significant_digits():
    assert [gpu_check.figure(x) for x in (0.0741, 1.234, 12.34, 123.4, 12345.6)] == \
        ["0.0741", "1.23", "12.3", "123", "12,346"]
    assert gpu_check.figure(math.nan) == "nan"


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_cuda_without_a_gpu_is_a_one_line_error(capsys):
    assert gpu_check.main(["--device", "cuda", "--params", str(REPO_ROOT / "params.yaml")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "python -m bench.gpu_check: error: device: cuda was requested but no CUDA device is available"


@needs_cuda
def test_the_gpu_agrees_with_the_cpu_at_the_paper_size(capsys):
    status, lines = run(capsys, "--device", "cuda", "--quick", "--domains", "csg2d", "csg3d", "--parts", "agree")
    assert status == 0 and lines[-1] == "paper profile: 2 parts ok on cuda"


@pytest.mark.slow
def test_the_quick_cpu_check_passes(capsys):
    """The issue's CPU check: every part of every domain (14 minutes at most on the 2-core machine)."""
    status, lines = run(capsys, "--device", "cpu", "--quick")
    assert status == 0 and lines[-1] == "paper profile: 21 parts ok on cpu"
