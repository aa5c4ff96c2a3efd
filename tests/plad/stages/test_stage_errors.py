"""Stage entry points turn the errors a user can fix into one line and exit status 1."""
import pytest

from plad.stages import evaluate, pretrain, synthesize


@pytest.mark.parametrize("module, section", [(synthesize, "synthesize"), (pretrain, "pretrain"),
                                             (evaluate, "evaluate")])
def test_unknown_key_is_a_one_line_error(tmp_path, capsys, module, section):
    p = tmp_path / "params.yaml"
    p.write_text(f"{section}:\n  base:\n    no_such_key: 1\n  csg2d: {{}}\n")
    assert module.main(["--params", str(p), "--section", f"{section}.csg2d"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no_such_key" in err and f"{section}.csg2d" in err and str(p) in err


@pytest.mark.parametrize("module, section", [(synthesize, "synthesize"), (pretrain, "pretrain"),
                                             (evaluate, "evaluate")])
def test_a_section_without_its_domain_is_a_one_line_error(tmp_path, capsys, module, section):
    p = tmp_path / "params.yaml"
    p.write_text(f"{section}:\n  base:\n    seed: 1\n  csg2d: {{}}\n")
    assert module.main(["--params", str(p)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"{section}: error: {p}: section '{section}' has one block per domain: name one, "
                   f"e.g. {section}.<domain> (csg2d)")
    assert module.main(["--params", str(p), "--section", f"{section}.csg3d"]) == 1
    assert capsys.readouterr().err.strip() == f"{section}: error: {p}: section '{section}.csg3d' is missing"


def test_pretrain_without_synthetic_programs_names_the_file(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text("pretrain:\n  csg2d: {}\n")
    assert pretrain.main(["--params", str(p), "--section", "pretrain.csg2d", "--root", str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err.strip()
    assert "synthesize stage" in err and str(tmp_path / "nothing" / "data" / "synthetic" / "csg2d.npz") in err


@pytest.mark.parametrize("content", [b"not an npz", b""])
def test_pretrain_with_a_corrupt_synthetic_file_names_the_file(tmp_path, capsys, content):
    p = tmp_path / "params.yaml"
    p.write_text("pretrain:\n  csg2d: {}\n")
    bad = tmp_path / "data" / "synthetic" / "csg2d.npz"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(content)
    assert pretrain.main(["--params", str(p), "--section", "pretrain.csg2d", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and "synthesize stage" in err


def test_evaluate_with_a_missing_checkpoint_names_the_file(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text("evaluate:\n  csg2d: {}\n")
    assert evaluate.main(["--params", str(p), "--section", "evaluate.csg2d", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no such checkpoint" in err and str(tmp_path / "runs" / "pretrain" / "csg2d" / "best.pt") in err
