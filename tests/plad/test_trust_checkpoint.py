"""Checkpoints hold tensors and plain data only: a crafted file cannot run code when loaded (issue 18)."""
from __future__ import annotations

import io
import os
import random

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.model.checkpoint import FORMAT, CheckpointError, convert, load_model, read_checkpoint, save_checkpoint
from plad.model.network import ModelConfig, PLADNet


def tiny(domain_name: str = "csg2d") -> PLADNet:
    d = get_domain(domain_name)
    torch.manual_seed(0)
    return PLADNet(ModelConfig(vocab_size=len(d.tokens), max_len=d.tokens.max_len, input_shape=d.shape,
                               enc_channels=(4, 8, 8, 8), d_model=32, n_layers=1, n_heads=2, dim_ff=32)).eval()


class _Payload:
    """Unpickling this calls os.system: the side effect shows whether loading ran code."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _crafted(path, marker):
    model = tiny()
    payload = {"format": FORMAT, "domain": "csg2d", "tokens": get_domain("csg2d").tokens.names,
               "config": model.cfg.to_dict(), "state_dict": model.state_dict(), "hook": _Payload(marker)}
    buf = io.BytesIO()
    torch.save(payload, buf)
    path.write_bytes(buf.getvalue())


def test_a_checkpoint_carrying_a_pickled_callable_is_refused_and_runs_nothing(tmp_path, capsys):
    from plad.serve.cli import main

    bad, marker = tmp_path / "bad.pt", tmp_path / "ran"
    _crafted(bad, marker)
    with pytest.raises(CheckpointError, match="holds objects other than tensors and plain data"):
        read_checkpoint(bad)
    assert not marker.exists()
    img = tmp_path / "in.npy"
    shape = np.zeros(get_domain("csg2d").shape, bool)
    shape[20:40, 20:40] = True
    np.save(img, shape)
    code = main(["infer", "csg2d", str(img), "--model", str(bad), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 1 and "holds objects other than tensors" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not marker.exists()
    assert not (tmp_path / "out").exists()


def test_a_generator_file_with_a_callable_is_refused(tmp_path):
    from plad.learn.ws import load_generator

    bad, marker = tmp_path / "gen.pt", tmp_path / "ran"
    buf = io.BytesIO()
    torch.save({"ws": {}, "hook": _Payload(marker)}, buf)
    bad.write_bytes(buf.getvalue())
    with pytest.raises(CheckpointError):
        load_generator(bad, torch.device("cpu"))
    assert not marker.exists()


def test_training_state_round_trips_as_plain_data(tmp_path):
    """A resumable last.pt (optimizer, RNG states) loads with weights_only=True and restores the RNGs."""
    from plad.learn.train import _rng_state, _set_rng_state

    model = tiny()
    opt = torch.optim.Adam(model.parameters())
    random.seed(1)
    np.random.seed(2)
    torch.manual_seed(3)
    path = save_checkpoint(tmp_path / "last.pt", model, "csg2d", get_domain("csg2d").tokens.names,
                           {"optimizer": opt.state_dict(), "rng": _rng_state(), "val": np.float64(0.5)})
    expect = (random.random(), np.random.rand(), torch.rand(1).item())
    payload = torch.load(path, weights_only=True)   # the safe reader accepts it
    _set_rng_state(payload["rng"])
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expect
    assert payload["val"] == 0.5 and isinstance(payload["val"], float)
    assert load_model(path)[1] == "csg2d"


def test_save_refuses_anything_but_plain_data(tmp_path):
    with pytest.raises(TypeError, match="extra.fn"):
        save_checkpoint(tmp_path / "x.pt", tiny(), "csg2d", get_domain("csg2d").tokens.names, {"fn": print})
    assert not (tmp_path / "x.pt").exists()


def test_old_checkpoints_are_converted_by_the_documented_command(tmp_path, capsys):
    """An older last.pt pickled NumPy's RNG state (an ndarray): refused, then converted once, then loadable."""
    from plad.model.checkpoint import main

    model = tiny()
    old = {"format": FORMAT, "domain": "csg2d", "tokens": get_domain("csg2d").tokens.names,
           "config": model.cfg.to_dict(), "state_dict": model.state_dict(),
           "rng": {"numpy": np.random.get_state()}}
    path = tmp_path / "old.pt"
    buf = io.BytesIO()
    torch.save(old, buf)
    path.write_bytes(buf.getvalue())
    with pytest.raises(CheckpointError, match="python -m plad.model.checkpoint convert"):
        read_checkpoint(path)
    assert main(["convert", str(path), str(tmp_path / "new.pt")]) == 0
    payload = read_checkpoint(tmp_path / "new.pt")
    assert torch.equal(payload["rng"]["numpy"][1], torch.from_numpy(old["rng"]["numpy"][1]))
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        convert(tmp_path / "missing.pt", tmp_path / "x.pt")
