"""Device, precision and host-to-device copies (plad/device.py); the CUDA-only checks skip without a GPU."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plad.config import ConfigError
from plad.device import BF16_LOSS_RTOL, FP32, Precision, resolve_precision, to_device
from tests.conftest import REPO_ROOT

CPU = torch.device("cpu")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def test_precision_values_resolve_per_device():
    assert resolve_precision("fp32", CPU) == Precision("cpu", None) == FP32
    assert resolve_precision("bf16", CPU) == Precision("cpu", torch.bfloat16)
    assert resolve_precision("auto", CPU) == FP32   # a CPU run keeps its numbers unless it opts in
    assert resolve_precision("bf16", CPU).name == "bf16" and FP32.name == "fp32"
    with pytest.raises(ValueError, match=r"precision 'fp16': use one of auto, bf16, fp32"):
        resolve_precision("fp16", CPU)


def test_fp32_adds_no_autocast_and_bf16_autocasts():
    x = torch.randn(4, 8)
    w = torch.randn(8, 3)
    with FP32.autocast():
        assert not torch.is_autocast_enabled("cpu")
        assert (x @ w).dtype == torch.float32
    with resolve_precision("bf16", CPU).autocast():
        assert torch.is_autocast_enabled("cpu")
        assert (x @ w).dtype == torch.bfloat16


@pytest.mark.parametrize("section, key", [("pretrain.csg3d", "pretrain"), ("finetune.csg2d", "finetune")])
def test_an_unknown_precision_is_a_config_error_naming_the_key(tmp_path, section, key):
    from plad.config import load_params
    from plad.config import section as build_section
    from plad.learn.pretrain import PretrainConfig
    from plad.stages.finetune import FinetuneStageConfig

    text = (REPO_ROOT / "params.yaml").read_text().replace("    precision: fp32\n", "    precision: half\n")
    (tmp_path / "params.yaml").write_text(text)
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "cpu.yaml").write_text("{}\n")
    cls = PretrainConfig if key == "pretrain" else FinetuneStageConfig
    with pytest.raises(ConfigError, match=rf"params.yaml: {section}: precision 'half': use one of auto, bf16, fp32"):
        build_section(load_params(tmp_path / "params.yaml"), section, cls)


def shipped_batch(domain: str, n: int = 8):
    """The shipped (trained) model of ``domain``, and a batch of synthetic shapes labelled with its own greedy
    programs: a trained network on programs it finds likely, where rounding shows most."""
    from plad.domains import get_domain
    from plad.domains.base import pad_programs
    from plad.model.checkpoint import load_model
    from plad.model.decode import greedy_decode

    model, _ = load_model(REPO_ROOT / "plad" / "shipped" / domain / "model.pt", CPU, expect_domain=domain)
    dom = get_domain(domain)
    shapes = dom.execute(pad_programs(dom.sample(n, np.random.default_rng(1))))
    labels = greedy_decode(model, dom.tokens, shapes)
    return model, (shapes, pad_programs(labels), torch.tensor([len(z) for z in labels]))


@pytest.mark.parametrize("domain", ["csg2d", "shapeassembly"])
def test_bf16_autocast_changes_the_loss_by_less_than_the_stated_tolerance(domain):
    model, batch = shipped_batch(domain)
    with torch.no_grad():
        fp32, _ = model.loss(*batch)
        with resolve_precision("bf16", CPU).autocast():
            bf16, _ = model.loss(*batch)
    assert fp32.dtype == bf16.dtype == torch.float32           # the cross-entropy sums in float32 either way
    change = abs(float(bf16) - float(fp32)) / float(fp32)
    assert 0 < change < BF16_LOSS_RTOL                         # the arithmetic changed, the loss hardly


def test_a_bf16_training_step_moves_the_weights_as_an_fp32_step_does():
    from plad.learn.train import train_step

    model, batch = shipped_batch("csg2d", 4)
    start = {k: v.clone() for k, v in model.state_dict().items()}
    moved = {}
    for precision in (FP32, resolve_precision("bf16", CPU)):
        model.load_state_dict(start)
        model.eval()   # no dropout: the two steps differ by their arithmetic only
        opt = torch.optim.SGD(model.parameters(), lr=0.1)
        loss, acc = train_step(model, opt, lambda b: model.loss(*b), batch, 1.0, precision)
        assert not loss.requires_grad and loss.dtype == torch.float32
        moved[precision.name] = torch.cat([(p.detach() - start[k]).flatten() for k, p in model.named_parameters()])
    cos = torch.nn.functional.cosine_similarity(moved["fp32"], moved["bf16"], dim=0)
    assert not torch.equal(moved["fp32"], moved["bf16"]) and float(cos) > 0.99


def test_to_device_on_the_cpu_copies_nothing():
    array = np.arange(6, dtype=np.int64).reshape(2, 3)
    t = to_device(array, CPU)
    array[0, 0] = 7
    assert t.dtype == torch.int64 and int(t[0, 0]) == 7      # shares the array's memory, as torch.from_numpy
    tensor = torch.ones(3)
    assert to_device(tensor, CPU) is tensor


@needs_cuda
def test_auto_is_bf16_on_a_gpu_that_computes_it_natively():
    native = torch.cuda.get_device_capability()[0] >= 8    # A100, H100, RTX 30xx and later; older GPUs emulate it
    assert resolve_precision("auto", torch.device("cuda")) == Precision("cuda", torch.bfloat16 if native else None)


@needs_cuda
def test_to_device_on_cuda_pins_and_copies_exactly():
    array = np.random.default_rng(0).random((64, 32, 32)) > 0.5
    t = to_device(array, torch.device("cuda"))
    assert t.device.type == "cuda" and torch.equal(t.cpu(), torch.from_numpy(array))


@needs_cuda
@pytest.mark.parametrize("domain", ["csg2d", "shapeassembly"])
def test_cuda_matches_cpu_in_fp32_and_bf16_stays_within_tolerance(domain):
    import copy

    model, batch = shipped_batch(domain)
    gpu = copy.deepcopy(model).cuda()
    cuda_batch = tuple(to_device(t, torch.device("cuda")) for t in batch)
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.no_grad():
            cpu_loss = float(model.loss(*batch)[0])
            cuda_loss = float(gpu.loss(*cuda_batch)[0])
            with resolve_precision("bf16", torch.device("cuda")).autocast():
                bf16_loss = float(gpu.loss(*cuda_batch)[0])
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32
    assert abs(cuda_loss - cpu_loss) / cpu_loss < 1e-3
    assert abs(bf16_loss - cpu_loss) / cpu_loss < BF16_LOSS_RTOL


def test_torch_threads_sets_the_count_for_the_block_and_restores_it():
    from plad.device import torch_threads

    before = torch.get_num_threads()
    with pytest.raises(RuntimeError, match="inside"):
        with torch_threads(1):
            assert torch.get_num_threads() == 1
            raise RuntimeError("inside")
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("domain", ["csg2d", "csg3d", "shapeassembly"])
def test_the_samplers_draw_the_same_programs_whatever_the_thread_count(domain):
    """Why synthesize may sample on one thread (plad.device.torch_threads): the programs are the same."""
    from plad.device import torch_threads
    from plad.domains import get_domain

    for name, sample in get_domain(domain).samplers().items():
        drawn = []
        for threads in (1, 2):
            with torch_threads(threads):
                drawn.append(sample(60, np.random.default_rng(7)))
        assert drawn[0] == drawn[1], name
