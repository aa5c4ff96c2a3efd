"""A checkpoint is checked before its network is built (issue 30): a missing entry, a config that is not its
domain's or that declares a huge network, weights of other names or shapes, NaN weights: each one line naming
what is wrong, never a traceback (exit status 1, plad.errors)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.model.checkpoint import (
    FORMAT,
    CheckpointError,
    check_checkpoint,
    load_model,
    network_digest,
    read_checkpoint,
)
from plad.serve.cli import main


def _pop_weight(p):
    p["state_dict"].pop("head.0.weight")


def _nan_weights(p):
    for v in p["state_dict"].values():
        if v.is_floating_point():
            v.fill_(float("nan"))


DAMAGE = {
    "missing domain": (lambda p: p.pop("domain"), "no 'domain' entry: not a complete PLAD checkpoint"),
    "missing tokens": (lambda p: p.pop("tokens"), "no 'tokens' entry"),
    "extra config key": (lambda p: p["config"].update(bogus=1), "unknown key(s) bogus in 'config'"),
    "n_heads 3": (lambda p: p["config"].update(n_heads=3), "must be divisible by n_heads 3"),
    "weight removed": (_pop_weight, "missing weights head.0.weight for its config"),
    "NaN weights": (_nan_weights, "holds NaN or infinite values"),
    "3D input shape": (lambda p: p["config"].update(input_shape=(32, 32, 32)),
                       "config.input_shape = (32, 32, 32), but a csg2d network has (64, 64)"),
    "max_len 1": (lambda p: p["config"].update(max_len=1), "config.max_len = 1, but a csg2d network has 14"),
    "17 GB model": (lambda p: p["config"].update(d_model=65536, dim_ff=65536), "more than the limit of 200,000,000"),
    "a weight of another shape": (lambda p: p["state_dict"].update(pos=torch.zeros(3, 3)),
                                  "weight pos is (3, 3), its config needs"),
}


@pytest.fixture(scope="module")
def good(tmp_path_factory, tiny_checkpoint):
    return read_checkpoint(tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "good.pt", "csg2d"))


def test_a_good_checkpoint_passes_and_loads(good, tmp_path):
    torch.save(good, tmp_path / "m.pt")
    cfg, domain = check_checkpoint(tmp_path / "m.pt", good, "csg2d")
    assert domain == "csg2d" and cfg.input_shape == (64, 64)
    model, _ = load_model(tmp_path / "m.pt")
    assert all(torch.equal(model.state_dict()[k], v) for k, v in good["state_dict"].items())


def test_the_network_digest_is_that_of_the_weights_not_of_the_files_seconds(good, tmp_path):
    a, b, c = (tmp_path / f"{n}.pt" for n in "abc")
    torch.save(good, a)
    other_seconds = copy.deepcopy(good)
    other_seconds["provenance"] = {"segments": [{"train_seconds": 1.8}]}
    torch.save(other_seconds, b)
    assert a.read_bytes() != b.read_bytes() and network_digest(a) == network_digest(b)
    other_weight = copy.deepcopy(good)
    next(iter(other_weight["state_dict"].values())).view(-1)[0] += 1
    torch.save(other_weight, c)
    assert network_digest(c) != network_digest(a)


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_each_damage_is_one_line_naming_it(good, tmp_path, case):
    damage, phrase = DAMAGE[case]
    payload = copy.deepcopy(good)
    damage(payload)
    assert payload["format"] == FORMAT
    torch.save(payload, tmp_path / "m.pt")
    with pytest.raises(CheckpointError) as err:
        load_model(tmp_path / "m.pt", expect_domain="csg2d")
    assert phrase in str(err.value) and "\n" not in str(err.value) and str(tmp_path / "m.pt") in str(err.value)


@pytest.mark.parametrize("case", ["NaN weights", "missing domain", "17 GB model"])
def test_infer_and_ship_report_it_in_one_line_with_status_1(good, tmp_path, capsys, case):
    damage, phrase = DAMAGE[case]
    payload = copy.deepcopy(good)
    damage(payload)
    torch.save(payload, tmp_path / "m.pt")
    shape = np.zeros((64, 64), bool)
    shape[20:40, 20:44] = True
    np.save(tmp_path / "in.npy", shape)
    assert main(["infer", "csg2d", str(tmp_path / "in.npy"), "--model", str(tmp_path / "m.pt"),
                 "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and phrase in err and not (tmp_path / "out").exists()
    (tmp_path / "metrics.json").write_text('{"domain": "csg2d", "test": {"mean": 1.0}}')
    assert main(["models", "ship", "csg2d", str(tmp_path / "m.pt"), "--metrics", str(tmp_path / "metrics.json"),
                 "--dest", str(tmp_path / "shipped")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and phrase in err and not (tmp_path / "shipped").exists()


def test_the_shipped_models_pass_the_checks():
    from plad.shipped import list_shipped

    for m in list_shipped():
        check_checkpoint(m.checkpoint, read_checkpoint(m.checkpoint), m.domain)
        assert get_domain(m.domain).shape
