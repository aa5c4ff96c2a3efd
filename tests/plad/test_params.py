"""params.yaml as one base per stage plus per-domain blocks, and profiles as short override files."""
import copy
import shutil
from pathlib import Path

import pytest
import yaml

from plad.config import BASE, PER_DOMAIN, STAGE_SECTIONS, ConfigError, load_params, merge, section
from tests.conftest import REPO_ROOT

REPO = REPO_ROOT
PROFILES = ("cpu", "smoke", "paper")


def stage_classes():
    from plad.config import SECTION_CLASSES, section_class

    assert tuple(SECTION_CLASSES) == STAGE_SECTIONS   # every stage section names the class it builds
    return {name: section_class(name) for name in STAGE_SECTIONS}


def project(tmp_path: Path, profile: str = "cpu", params: dict | None = None, profiles: dict | None = None) -> Path:
    """A copy of the repository's params.yaml and profiles/ with ``profile`` chosen (as ``dvc exp run -S`` does)."""
    data = yaml.safe_load((REPO / "params.yaml").read_text()) if params is None else params
    data = {**data, "profile": profile}
    (tmp_path / "profiles").mkdir(exist_ok=True)
    for name in PROFILES:
        shutil.copy(REPO / "profiles" / f"{name}.yaml", tmp_path / "profiles" / f"{name}.yaml")
    for name, body in (profiles or {}).items():
        (tmp_path / "profiles" / f"{name}.yaml").write_text(yaml.safe_dump(body))
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def resolved(params) -> dict:
    """Every stage config of every domain, as plain data: {"pretrain.csg2d": {...}, "report": {...}, ...}."""
    import dataclasses

    out = {}
    for name, cls in stage_classes().items():
        names = [f"{name}.{d}" for d in params[name]] if name in PER_DOMAIN else [name]
        for n in names:
            out[n] = dataclasses.asdict(section(params, n, cls))
    return out


@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_builds_every_stage_of_every_domain(tmp_path, profile):
    params = load_params(project(tmp_path, profile))
    configs = resolved(params)
    for d in params["domains"]:
        for name in PER_DOMAIN:
            assert configs[f"{name}.{d}"]["domain"] == d
        assert list(configs[f"finetune.{d}"]["methods"]) == params["methods"]  # each DVC matrix entry has its key
    assert configs["prepare"]["domains"] == configs["report"]["domains"] == params["domains"]
    assert configs["report"]["profile"] == profile
    assert (REPO / "params.yaml").read_text().count("\nprofile: cpu\n") == 1   # the default profile


def test_the_cpu_profile_changes_nothing(tmp_path):
    assert yaml.safe_load((REPO / "profiles" / "cpu.yaml").read_text()) == {}


def test_base_then_domain_then_profile_base_then_profile_domain():
    params = {"pretrain": {"base": {"seed": 1, "model": {"d_model": 8, "n_layers": 2}, "train": {"lr": 0.1}},
                           "csg2d": {"model": {"d_model": 16}}, "csg3d": {}}}
    profile = {"pretrain": {"base": {"model": {"d_model": 4}, "seed": 2}, "csg3d": {"model": {"n_layers": 5}}}}
    with_profile = merge(params["pretrain"]["base"], params["pretrain"]["csg2d"], profile["pretrain"]["base"])
    assert with_profile == {"seed": 2, "model": {"d_model": 4, "n_layers": 2}, "train": {"lr": 0.1}}
    assert params["pretrain"]["base"]["model"] == {"d_model": 8, "n_layers": 2}   # inputs untouched
    assert merge({"a": [1, 2], "m": {"x": 1}}, {"a": [3], "m": None}) == {"a": [3], "m": None}  # only mappings merge


def test_load_params_resolves_blocks_and_the_profile(tmp_path):
    params = {"profile": "p", "domains": ["csg2d", "csg3d"],
              "pretrain": {"base": {"seed": 1, "model": {"d_model": 8, "n_layers": 2}},
                           "csg2d": {"model": {"d_model": 16}}, "csg3d": {}},
              "report": {"methods": ["sp"]}}
    p = project(tmp_path, "p", params, {"p": {"pretrain": {"base": {"model": {"d_model": 4}},
                                                           "csg3d": {"model": {"n_layers": 5}}}}})
    got = load_params(p)
    assert got["pretrain"] == {"csg2d": {"seed": 1, "model": {"d_model": 4, "n_layers": 2}, "domain": "csg2d"},
                               "csg3d": {"seed": 1, "model": {"d_model": 4, "n_layers": 5}, "domain": "csg3d"}}
    assert got["report"] == {"methods": ["sp"], "domains": ["csg2d", "csg3d"], "profile": "p"}
    assert got.source("pretrain.csg2d") == f"{p} with {tmp_path / 'profiles' / 'p.yaml'}"
    assert got.source("report") == str(p)


@pytest.mark.parametrize("override, message", [
    ({"pretrain": {"base": {"model": {"d_modle": 3}}}}, r"p.yaml: pretrain.base.model.d_modle is not set in params"),
    ({"pretrain": {"csg3d": {"seed": 3}}}, r"p.yaml: pretrain.csg3d is not a block of .*params.yaml"),
    ({"domains": ["csg2d"]}, r"p.yaml: domains cannot be set by a profile \(dvc.yaml reads it from params.yaml\)"),
    ({"pretrian": {}}, r"p.yaml: unknown section pretrian"),
    ({"report": {"methods": ["sp"]}}, r"p.yaml: section report is not in"),
    ({"pretrain": {"csg2d": {"domain": "csg3d"}}}, r"p.yaml: pretrain.csg2d.domain: not a key to set"),
])
def test_a_profile_only_changes_keys_params_sets(tmp_path, override, message):
    params = {"pretrain": {"base": {"seed": 1, "model": {"d_model": 8}}, "csg2d": {}}}
    with pytest.raises(ConfigError, match=message):
        load_params(project(tmp_path, "p", params, {"p": override}))


def test_a_profiles_star_entry_applies_to_every_entry_params_sets_those_added_later_too(tmp_path):
    # the paper profile's "no count of rounds per method": a method added to params.yaml needs no line there
    params = {"profile": "p", "domains": ["csg2d"],
              "finetune": {"base": {"methods": {"a": {"method": "st", "max_rounds": 3}, "rl": {"method": "rl"}}},
                           "csg2d": {"methods": {"b": {"method": "lest", "max_rounds": 2}}}}}
    profile = {"finetune": {"base": {"methods": {"*": {"max_rounds": None}, "a": {"method": "lest"}}},
                            "csg2d": {"methods": {"b": {"max_rounds": 7}}}}}
    got = load_params(project(tmp_path, "p", params, {"p": profile}))["finetune"]["csg2d"]["methods"]
    assert got == {"a": {"method": "lest", "max_rounds": None}, "rl": {"method": "rl", "max_rounds": None},
                   "b": {"method": "lest", "max_rounds": 7}}
    profile["finetune"]["base"]["methods"]["*"] = {"max_roudns": None}   # still only keys params.yaml sets
    with pytest.raises(ConfigError, match=r"p.yaml: finetune.base.methods.\*.max_roudns is not set in params"):
        load_params(project(tmp_path, "p", params, {"p": profile}))


def test_the_paper_profile_runs_every_method_to_its_patience(tmp_path):
    params = load_params(project(tmp_path, "paper"))
    for d in params["domains"]:
        assert {k: m.get("max_rounds") for k, m in params["finetune"][d]["methods"].items()} == \
            dict.fromkeys(params["methods"])


def test_params_errors_name_the_file_and_key(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("profile: nothere\n")
    with pytest.raises(ConfigError, match=r"params.yaml: profile 'nothere': no such file .*profiles/nothere.yaml"):
        load_params(p)
    p.write_text("domains: [csg2d]\nprepare:\n  domains: [csg3d]\n")
    with pytest.raises(ConfigError, match=r"prepare.domains: not a key to set here; its one home is the top-level"):
        load_params(p)
    p.write_text("pretrain:\n  domain: csg2d\n")
    with pytest.raises(ConfigError, match=r"pretrain.domain = 'csg2d': expected a block"):
        load_params(p)
    # a wrong value from a profile: the message names both files
    q = project(tmp_path, "p", {"pretrain": {"base": {"seed": 1}, "csg2d": {}}},
                {"p": {"pretrain": {"base": {"seed": "x"}}}})
    with pytest.raises(ConfigError, match=r"params.yaml with .*profiles/p.yaml: pretrain.csg2d.seed = 'x'"):
        section(load_params(q), "pretrain.csg2d", stage_classes()["pretrain"])


def test_a_profile_argument_replaces_the_files_profile_key(tmp_path):
    # what a flow run's `profile` parameter does (flows.finetune, flows.deploy): as -S profile=... would
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    path = project(tmp_path / "a", "cpu")
    smoke = load_params(path, profile="smoke")
    assert smoke == load_params(project(tmp_path / "b", "smoke")) != load_params(path)
    assert smoke.profile_file == tmp_path / "a" / "profiles" / "smoke.yaml"
    assert smoke["pretrain"]["csg2d"]["train"]["max_epochs"] == 2 and smoke["report"]["profile"] == "smoke"
    with pytest.raises(ConfigError, match=r"^.*/a/params.yaml: profile 'gpu': no such file .*/a/profiles/gpu.yaml$"):
        load_params(path, profile="gpu")


def leaves(node, path=()):
    if isinstance(node, dict) and node:
        for k, v in node.items():
            yield from leaves(v, (*path, k))
    else:
        yield path


def value_at(doc: dict, path: tuple):
    for part in path:
        doc = doc[part]
    return doc


def without(doc: dict, path: tuple) -> dict:
    doc = copy.deepcopy(doc)
    node = doc
    for part in path[:-1]:
        node = node[part]
    del node[path[-1]]
    return doc


def test_every_domain_block_key_and_every_profile_key_changes_something(tmp_path):
    """One home per knob: no key repeats a value it would have anyway (a domain block its base, a profile cpu).
    An empty mapping sets no value: a domain block holds one where DVC tracks the key (finetune's `methods`)."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    for name in PER_DOMAIN:
        for block, body in params[name].items():
            for path in leaves(body) if block != BASE else []:
                if not path or value_at(body, path) == {}:
                    continue
                base = params[name][BASE]
                got = merge(base, body)
                assert merge(base, without(body, path)) != got, f"params.yaml: {name}.{block}.{'.'.join(path)}"
    for profile in ("smoke", "paper"):
        over = yaml.safe_load((REPO / "profiles" / f"{profile}.yaml").read_text())
        full = resolved(load_params(project(tmp_path, profile)))
        for path in leaves(over):
            (tmp_path / "profiles" / f"{profile}.yaml").write_text(yaml.safe_dump(without(over, path)))
            assert resolved(load_params(tmp_path / "params.yaml")) != full, f"{profile}: {'.'.join(path)}"
        shutil.copy(REPO / "profiles" / f"{profile}.yaml", tmp_path / "profiles" / f"{profile}.yaml")
    assert set(params) - {"profile", "domains", "methods", "beams"} == set(STAGE_SECTIONS)
