"""The pyfunc model's predict reads its input by the rules of every command (plad.data.inputs) and checks its
beam as the CLI does (issue 30): an empty, a full or an all-NaN target is an error row, the rest inferred."""
from __future__ import annotations

import numpy as np
import pytest

from plad.domains import get_domain


@pytest.fixture(scope="module")
def model(tmp_path_factory, tiny_checkpoint):
    from plad.tracking.serving import load_checkpoint_pyfunc

    ckpt = tiny_checkpoint(tmp_path_factory.mktemp("pyfunc") / "model.pt", "csg2d")
    return load_checkpoint_pyfunc(ckpt, beam=2)


def test_bad_targets_are_error_rows_and_the_others_are_inferred(model):
    domain = get_domain("csg2d")
    good = np.zeros(domain.shape, bool)
    good[20:40, 16:48] = True
    batch = np.stack([good, np.zeros_like(good), np.ones_like(good), good]).astype(np.float32)
    batch[2] = np.nan                                               # all-NaN (was scored 16.0)
    out = model.predict(batch)
    assert list(out.columns) == ["program", "chamfer", "error"] and len(out) == 4
    assert out["error"].isna().tolist() == [True, False, False, True]
    assert out["program"][0] == out["program"][3] and domain.parse(out["program"][0])
    assert out["error"][1].startswith("the shape is empty") and out["program"].isna()[1]
    assert out["error"][2] == "the array holds NaN or infinite values" and np.isnan(out["chamfer"][2])
    full = model.predict(np.ones((1, *domain.shape), bool))
    assert full["error"][0].startswith("the shape fills the whole grid")
    # a list of arrays of other sizes: each fitted to the canvas, as `plad infer` fits a drawing
    listed = model.predict([good, np.kron(good, np.ones((2, 2), bool))])
    assert listed["error"].isna().all() and listed["program"][0] == listed["program"][1]


@pytest.mark.parametrize("beam", [0, -1, 101, 10 ** 9])
def test_a_beam_outside_1_to_max_beam_is_refused(model, beam):
    good = np.zeros((64, 64), bool)
    good[20:40, 16:48] = True
    with pytest.raises(ValueError, match=r"a beam width is an integer from 1 to 100 \(MAX_BEAM\)"):
        model.predict(good, params={"beam": beam})
