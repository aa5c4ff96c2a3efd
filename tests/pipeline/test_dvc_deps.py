"""dvc.yaml is honest: every stage depends on the code it runs, the params it reads, and the layout's paths.

The stages are read with DVC's own parser (templates expanded for every
domain and method). A stage's code is the import closure of its command's
module: every ``import``/``from`` anywhere in a file of ``plad/`` or
``flows/`` (inside functions too), resolved to files, plus the plugin
module of each domain it loads through the registry (its own domain, or
every domain of ``domains``) with that module's closure. dvc.yaml folds the
closure: a stage may depend on a whole package of :data:`FOLDED` (an edit
anywhere in it then reruns the stage, though the stage imports only part of
it); any other code dependency, a file or a folder, must be code the stage
runs (editing ``plad/eval/report.py`` must not rerun pretraining). Params are
tracked key by key: editing one fine-tuning method's entry makes that
method's stages stale and no other, as DVC itself finds them.
"""
from __future__ import annotations

import importlib
import shlex
import shutil
import subprocess
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import pytest
import yaml

from plad.config import INJECTED, PER_DOMAIN, load_params
from plad.eval.report import amortization_keys
from plad.layout import (
    AMORTIZATION_PLOT,
    AMORTIZATION_TABLE,
    BEST,
    CONVERGENCE,
    FLOOR,
    GRID,
    HISTORY,
    LAST,
    METRICS,
    PROVENANCE,
    REPORT,
    SEARCH,
    SP,
    SUMMARY,
    TABLE,
    Layout,
    eval_key,
    programs_csv,
    search_key,
)
from tests.conftest import REPO_ROOT
from tests.imports import imported_modules

REPO = REPO_ROOT
PACKAGES = ("plad", "flows")   # where the project's code lives; anything else is a third-party import

pytestmark = pytest.mark.skipif(shutil.which("dvc") is None, reason="dvc is not installed")


# -- the import closure -----------------------------------------------------------------------------
#: modules that use another module's file without importing it: plad.tracking.serving hands MLflow the path of
#: plad/tracking/pyfunc_model.py (a models-from-code file, copied into every logged model), so a stage that logs
#: models depends on that file as if it imported it
RUN_BY_PATH = {"plad.tracking.serving": ["plad.tracking.pyfunc_model"]}


def test_the_files_run_by_path_are_those_the_modules_name():
    from plad.tracking import serving

    assert serving.MODEL_CODE == module_file(RUN_BY_PATH["plad.tracking.serving"][0])


def module_file(name: str) -> Path | None:
    path = REPO / Path(*name.split("."))
    for candidate in (path / "__init__.py", path.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


@cache
def closure(module: str) -> frozenset[str]:
    """Repository-relative files of ``module`` and everything it imports, transitively (packages' __init__ too)."""
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name.split(".")[0] not in PACKAGES:
            continue
        parts = name.split(".")
        for prefix in (".".join(parts[:i]) for i in range(1, len(parts) + 1)):   # importing a.b runs a/__init__
            path = module_file(prefix)
            if path is None or prefix in seen:
                continue
            seen[prefix] = path
            package = prefix if path.name == "__init__.py" else prefix.rpartition(".")[0]
            todo.extend(imported_modules(path.read_text(), package))   # every import, at any depth
            todo.extend(RUN_BY_PATH.get(prefix, []))
    return frozenset(str(p.relative_to(REPO)) for p in seen.values())


#: the packages a stage may depend on as a whole folder, an over-approximation of its import closure that keeps
#: dvc.yaml readable; plad/eval and plad/stages are listed file by file (editing the report, or one stage's module,
#: reruns only the stages that run it), and so are the top-level modules (the folder plad holds everything)
FOLDED = ("plad/data", "plad/domains", "plad/learn", "plad/metrics", "plad/model", "plad/rewrite", "plad/tracking")


def code_files() -> set[str]:
    return {str(p.relative_to(REPO)) for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")
            if "__pycache__" not in p.parts}


# -- the stages as DVC sees them ---------------------------------------------------------------------
@dataclass
class Stage:
    name: str
    cmd: str
    deps: list[str] = field(default_factory=list)
    params: dict[str, list[str]] = field(default_factory=dict)   # params file -> keys ([]: the whole file)
    outs: list[str] = field(default_factory=list)

    @property
    def group(self) -> str:
        return self.name.split("@")[0]

    @property
    def argv(self) -> list[str]:
        return shlex.split(self.cmd)

    def option(self, name: str, default: str | None = None) -> str | None:
        argv = self.argv
        return argv[argv.index(name) + 1] if name in argv else default

    @property
    def sets(self) -> dict[str, str]:
        argv = self.argv
        return dict(argv[i + 1].split("=", 1) for i, a in enumerate(argv) if a == "--set")

    @property
    def module(self) -> str:
        assert self.argv[:3] == ["python", "-m", self.argv[2]], self.cmd
        return self.argv[2]

    @property
    def section(self) -> str:
        return self.option("--section", self.module.rsplit(".", 1)[1])


@cache
def stages() -> tuple[Stage, ...]:
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    out = []
    with Repo(str(REPO)) as repo:
        for st in repo.index.stages:
            stage = Stage(st.addressing, st.cmd)
            for dep in st.deps:
                if isinstance(dep, ParamsDependency):
                    stage.params[dep.def_path] = list(dep.params)
                else:
                    stage.deps.append(dep.def_path)
            stage.outs = [o.def_path for o in st.outs]   # outs, metrics and plots
            out.append(stage)
    return tuple(out)


@cache
def params():
    return load_params(REPO / "params.yaml")


def domains_of(stage: Stage) -> list[str]:
    """The domains whose plugins the stage loads: its own, or every domain it is configured with."""
    section = params()
    for part in stage.section.split("."):
        section = section[part]
    return [section["domain"]] if "domain" in section else list(section["domains"])


def method_plugin_modules() -> list[str]:
    """The modules of the fine-tuning methods and sources registered in plad.learn.method_registry (imported by
    name on first use, as domain plugins are): a fine-tuning stage loads its method's, and one template serves
    every method."""
    from plad.learn.method_registry import plugin_modules

    return plugin_modules()


def code_of(stage: Stage) -> frozenset[str]:
    from plad.domains import plugin_module

    files = set(closure(stage.module))
    for domain in domains_of(stage):
        files |= closure(plugin_module(domain))
    if stage.group == "finetune":
        for module in method_plugin_modules():
            files |= closure(module)
    return frozenset(files)


@cache
def shared_plugin_code() -> frozenset[str]:
    """What the registered plugins import outside their own packages: a per-domain template depends on all of it."""
    from plad.domains import domain_names, plugin_module

    files = set()
    for name in domain_names():
        own = str(module_file(plugin_module(name)).parent.relative_to(REPO))
        files |= {f for f in closure(plugin_module(name)) if not covers(own, f)}
    return frozenset(files)


def is_code(path: str) -> bool:
    """A module or package of the code; a data file inside the package (the shipped networks' index) is not."""
    return path.split("/")[0] in PACKAGES and (path.endswith(".py") or "." not in Path(path).name)


def covers(dep: str, path: str) -> bool:
    return path == dep or path.startswith(dep.rstrip("/") + "/")


def test_the_pipeline_has_every_stage_of_every_domain_and_method():
    p = params()
    names = {s.name for s in stages()}
    groups = ("synthesize", "pretrain", "evaluate", "search_only", "evaluate_finetuned", "evaluate_refined",
              "search_effort", "evaluate_effort", "label", "teach", "evaluate_taught", "evaluate_taught_refined")
    assert names == {"prepare", "report"} | {f"{g}@{d}" for g in groups for d in p["domains"]} | \
        {f"finetune@{d}-{m}" for d in p["domains"] for m in p["methods"]}


def test_every_stage_depends_on_the_code_it_imports_and_no_other():
    files = code_files()
    for stage in stages():
        needed = code_of(stage)
        deps = [d for d in stage.deps if is_code(d)]
        stale = [d for d in deps if not (REPO / d).exists()]
        assert not stale, f"{stage.name}: dvc.yaml names code that does not exist: {stale}"
        missing = sorted(f for f in needed if not any(covers(d, f) for d in deps))
        assert not missing, f"{stage.name} imports files dvc.yaml does not list as its deps: {missing}"
        allowed = needed | shared_plugin_code()
        for dep in deps:
            under = {f for f in files if covers(dep, f)}
            assert under & needed, f"{stage.name}: dep {dep} covers no code the stage imports"
            if any(covers(folded, dep) for folded in FOLDED):
                continue   # a package (or a part of one) that may be over-covered
            unneeded = sorted(under - allowed)
            assert not unneeded, f"{stage.name}: dep {dep} covers code the stage does not import: {unneeded}"


def test_editing_the_report_code_reruns_only_the_report():
    users = {s.name for s in stages() if any(covers(d, "plad/eval/report.py") for d in s.deps)}
    assert users == {"report"}


def test_editing_a_stage_module_reruns_only_the_stages_that_run_it():
    for path in sorted(f for f in code_files() if f.startswith("plad/stages/") and not f.endswith("__init__.py")):
        users = {s.name for s in stages() if any(covers(d, path) for d in s.deps)}
        runners = {s.name for s in stages() if path in code_of(s)}
        assert users == runners, f"editing {path} reruns {sorted(users - runners)}, which do not run it"


def read_keys(stage: Stage) -> set[str]:
    """Dotted leaf keys of params.yaml the stage's config is built from (its method's entry only)."""
    raw = yaml.safe_load((REPO / "params.yaml").read_text())

    def leaves(node, prefix):
        if isinstance(node, dict) and node:
            for k, v in node.items():
                yield from leaves(v, f"{prefix}.{k}")
        else:
            yield prefix

    top, _, domain = stage.section.partition(".")
    if top in PER_DOMAIN:
        keys = set(leaves(raw[top].get("base"), f"{top}.base")) | set(leaves(raw[top][domain], f"{top}.{domain}"))
    else:
        keys = set(leaves(raw[top], top))
    keys |= {k for k in INJECTED.get(top, ()) if k in raw}
    # top-level keys a stage reads itself (e.g. evaluate_finetuned: every method's model and the sweep's beams)
    keys |= {k for k in getattr(importlib.import_module(stage.module), "TOP_LEVEL_PARAMS", ()) if k in raw}
    if top == "finetune":   # a fine-tuning stage reads the entry of its method only
        method = stage.sets["key"]
        keys = {k for k in keys if ".methods." not in k or k.split(".methods.")[1].split(".")[0] == method}
    return keys


def test_every_stage_depends_on_the_params_it_reads_and_on_no_key_it_overrides():
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    profile_file = f"profiles/{raw['profile']}.yaml"
    for stage in stages():
        declared = stage.params.get("params.yaml", [])
        reads = read_keys(stage)
        missing = sorted(k for k in reads if not any(covers(d.replace(".", "/"), k.replace(".", "/"))
                                                     for d in declared))
        assert not missing, f"{stage.name} reads params dvc.yaml does not declare: {missing}"
        for key in declared:
            assert any(covers(key.replace(".", "/"), k.replace(".", "/")) for k in reads) or \
                key == stage.section, f"{stage.name}: declares {key}, which it does not read"
        top, _, domain = stage.section.partition(".")
        for key in stage.sets:   # a key the command sets is not read from params.yaml
            assert not any(k.endswith(f".{key}") or f".{key}." in k for k in reads), \
                f"{stage.name} sets {key} on its command line and reads it from params.yaml"
        assert stage.params.get(profile_file) == [], f"{stage.name} must depend on the whole {profile_file}"
        if stage.group == "finetune":   # editing one method reruns only its stages
            others = [k for k in raw["finetune"]["base"]["methods"] if k != stage.sets["key"]]
            assert not any(covers(d.replace(".", "/"), f"finetune/{block}/methods/{m}")
                           for d in declared for m in others for block in ("base", domain)), \
                f"{stage.name} depends on the entries of other methods"


# -- params tracked key by key: what an edit makes stale, as DVC finds it ----------------------------------------
@pytest.fixture(scope="module")
def stale_after(tmp_path_factory):
    """``stale_after(edit)``: the stages whose params DVC finds changed once params.yaml is edited by ``edit`` (a
    function of its parsed mapping). The pipeline's definition (dvc.yaml, params.yaml, the profiles) is copied into
    a fresh DVC repository, where each stage's params are recorded as a run records them in dvc.lock."""
    from dvc.dependency.param import MissingParamsError
    from dvc.repo import Repo

    root = tmp_path_factory.mktemp("pipeline")
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, root / name)
    shutil.copytree(REPO / "profiles", root / "profiles")
    Repo.init(str(root), no_scm=True).close()
    with Repo(str(root)) as repo:
        probed = list(repo.index.stages)
        for st in probed:
            for dep in st.params:
                try:
                    dep.save()
                except MissingParamsError as err:
                    pytest.fail(f"{st.name}: {err} Every block of finetune sets the keys dvc.yaml tracks, "
                                f"its `methods` an entry for every method ({{}} where it keeps base's)")
        original = (root / "params.yaml").read_text()

        def stale(edit) -> set[str]:
            data = yaml.safe_load(original)
            edit(data)
            (root / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
            try:
                return {st.name for st in probed if any(dep.workspace_status() for dep in st.params)}
            finally:
                (root / "params.yaml").write_text(original)

        yield stale


def more_rounds(block: str, method: str):
    """An edit of params.yaml: one more round for ``method`` in ``finetune.<block>`` (its first, if it sets none)."""
    def edit(data):
        entry = data["finetune"][block]["methods"][method]
        entry["max_rounds"] = (entry.get("max_rounds") or 0) + 1
    return edit


def test_editing_one_methods_rounds_makes_only_its_stages_stale(stale_after):
    """Every method's entry of finetune.base, and in each domain's block one method's (each check reads params.yaml
    once per stage, so not all of them: every domain block sets every entry, or the fixture fails)."""
    p = params()
    assert stale_after(lambda data: None) == set()
    for method in p["methods"]:
        assert stale_after(more_rounds("base", method)) == {f"finetune@{d}-{method}" for d in p["domains"]}, method
    for domain, method in zip(p["domains"], p["methods"]):   # rl, whose entries are {}, then methods with rounds
        assert stale_after(more_rounds(domain, method)) == {f"finetune@{domain}-{method}"}, (domain, method)


def _levels(stage: Stage) -> list[str]:
    """The effort levels a stage's command runs (its ``--set effort_levels=[...]``)."""
    return yaml.safe_load(stage.sets["effort_levels"])


def test_the_effort_stages_run_the_reports_levels():
    """search_effort runs every level of report.efforts.levels but default (search_only's), evaluate_effort every
    level: the report's curve is what the pipeline computes."""
    levels = params()["report"]["efforts"]["levels"]
    by_group = {s.group: _levels(s) for s in stages() if s.group in ("search_effort", "evaluate_effort")}
    assert by_group == {"search_effort": [lv for lv in levels if lv != "default"], "evaluate_effort": levels}


# -- the layout ----------------------------------------------------------------------------------------
def expected_files(stage: Stage, layout: Layout) -> tuple[set[str], set[str]]:
    """(inputs, outputs) of a stage as the layout places them."""
    from plad.domains import get_domain

    p = params()
    rel = lambda paths: {str(x) for x in paths}  # noqa: E731
    domain = stage.section.partition(".")[2]
    method = stage.sets.get("method", stage.sets.get("key", SP))
    if stage.group == "prepare":
        sources = {get_domain(d).targets for d in p["domains"]}
        return set(), rel([*(layout.prepared(d) for d in p["domains"]),
                           *(layout.prepared_summary(d) for d in p["domains"]),
                           *(layout.prepared_dir / f for s in sources for f in s.files)])
    if stage.group == "synthesize":
        return set(), rel([layout.synthetic(domain), layout.synthetic_summary(domain)])
    if stage.group == "pretrain":
        out = layout.pretrain_dir(domain)
        # the prepared real shapes: the input-dependence diagnostic's real validation shapes
        # and the index of the shipped pretrained networks, which `init: shipped` continues
        return rel([layout.synthetic(domain), layout.prepared(domain), Path("plad/shipped/pretrained.json")]), \
            rel([out / LAST, out / BEST, out / HISTORY, out / SUMMARY, out / PROVENANCE])
    if stage.group == "search_only":
        out = layout.eval_dir(SEARCH, domain)
        splits = p["search_only"][domain]["splits"]
        return rel([layout.prepared(domain)]), rel([*(out / programs_csv(s) for s in splits), out / METRICS])
    if stage.group == "search_effort":   # a result per effort level, in one stage
        outs = [layout.eval_dir(search_key(lv), domain) / f for lv in _levels(stage)
                for f in (*map(programs_csv, p["search_only"][domain]["splits"]), METRICS)]
        return rel([layout.prepared(domain)]), rel(outs)
    if stage.group == "evaluate_effort":
        outs = [layout.eval_dir(eval_key(method, effort=lv), domain) / f for lv in _levels(stage)
                for f in (*map(programs_csv, p["evaluate"][domain]["splits"]), GRID, METRICS)]
        return rel([layout.finetune_dir(domain, method), layout.prepared(domain)]), rel(outs)
    if stage.group == "evaluate_finetuned":   # every method's model, then the sweep's beams, in one stage
        sweep = stage.option("--sweep-method")
        keys = [*p["methods"], *(eval_key(sweep, beam=b) for b in p["beams"])]
        splits = p["evaluate"][domain]["splits"]
        outs = [layout.eval_dir(k, domain) / f for k in keys for f in (*map(programs_csv, splits), GRID, METRICS)]
        return rel([*(layout.finetune_dir(domain, m) for m in p["methods"]), layout.prepared(domain)]), rel(outs)
    if stage.group == "label":
        return rel([layout.prepared(domain)]), rel([layout.labels(domain), layout.labels_dir / f"{domain}.json"])
    if stage.group == "teach":
        # the networks its init may name: the shipped SP (pretrained) and the kept search-seeded and taught ones
        # with their indexes
        starts = [Path(f"plad/shipped/{domain}/pretrained.pt"), Path(f"plad/shipped/{domain}/search_seeded.pt"),
                  Path("plad/shipped/search_seeded.json"), Path(f"plad/shipped/{domain}/taught.pt"),
                  Path("plad/shipped/taught.json")]
        return rel([layout.labels(domain), layout.prepared(domain), *starts]), \
            rel([layout.finetune_dir(domain, "taught"), layout.finetune_summary(domain, "taught")])
    if stage.group in ("evaluate", "evaluate_refined", "evaluate_taught", "evaluate_taught_refined"):
        sweep = stage.sets.get("sweep_beam")
        out = layout.eval_dir(eval_key(method, int(sweep) if sweep else None, stage.sets.get("refine") == "true"),
                              domain)
        splits = p["evaluate"][domain]["splits"]
        model = layout.model(domain, method) if method == SP else layout.finetune_dir(domain, method)
        # SP's metrics record how its pretraining ended (a fine-tuned model's summary is in its run folder)
        models = [model, layout.pretrain_dir(domain) / SUMMARY] if method == SP else [model]
        outs = [*(out / programs_csv(s) for s in splits), out / GRID, out / METRICS]
        if method == SP:   # the floor baseline is evaluated with SP
            floor = layout.eval_dir(FLOOR, domain)
            outs += [*(floor / programs_csv(s) for s in splits), floor / METRICS]
        return rel([*models, layout.prepared(domain)]), rel(outs)
    if stage.group == "finetune":
        return rel([layout.model(domain), layout.prepared(domain)]), \
            rel([layout.finetune_dir(domain, method), layout.finetune_summary(domain, method)])
    if stage.group == "report":
        rows = [*p["report"]["methods"], *p["report"]["per_round"].values()]
        ins = [layout.eval_dir(m, d) / METRICS for m in rows for d in p["domains"]]
        method, efforts = p["report"]["amortization"]["method"], p["report"]["efforts"]
        timed = [*p["report"]["beyond"], *(k for k, _ in amortization_keys(method, p["beams"], efforts["levels"])),
                 *(k for lv in efforts["table"] for k in (search_key(lv), eval_key(method, effort=lv)))]
        ins += [layout.eval_dir(k, d) / METRICS for k in timed for d in p["domains"]]
        ins += [layout.finetune_dir(d, m) for m in rows if m != SP for d in p["domains"]]
        ins += [layout.finetune_summary(d, m) for m in rows if m != SP for d in p["domains"]]
        ins += [layout.model(d) for d in p["domains"]]   # the champion may be the pretrained model
        # where each column's numbers come from: SP's pretraining and the floor
        ins += [layout.pretrain_dir(d) / SUMMARY for d in p["domains"]]
        ins += [layout.eval_dir(FLOOR, d) / METRICS for d in p["domains"]]
        out = layout.results_dir
        return rel(ins), rel([out / TABLE, out / CONVERGENCE, out / REPORT, out / AMORTIZATION_TABLE,
                              out / AMORTIZATION_PLOT])
    raise AssertionError(f"no layout known for stage {stage.name}")


def test_dvc_paths_are_the_layouts():
    layout = Layout(Path(""))   # relative paths, as dvc.yaml writes them
    for stage in stages():
        inputs, outputs = expected_files(stage, layout)
        assert set(stage.outs) == outputs, f"{stage.name}: dvc.yaml outs {sorted(stage.outs)} != layout {outputs}"
        data = [d for d in stage.deps if not is_code(d)]
        uncovered = sorted(f for f in inputs if not any(covers(d, f) for d in data))
        assert not uncovered, f"{stage.name} reads {uncovered}, not among its dvc.yaml deps {data}"
        for dep in data:
            assert any(covers(dep, f) for f in inputs), f"{stage.name}: dep {dep} is none of its inputs {inputs}"


def test_no_output_in_the_dvc_cache_is_also_tracked_by_git():
    """A DVC-cached output that git also tracks stops every `dvc repro` of its stage ("already tracked by
    SCM"), e.g. a file committed from a run in another clone without its .gitignore entry."""
    from dvc.repo import Repo

    tracked = set(subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True,
                                 check=True).stdout.splitlines())
    with Repo(str(REPO)) as repo:
        both = sorted(o.def_path for st in repo.index.stages for o in st.outs
                      if o.use_cache and o.def_path in tracked)
    assert not both, f"in the DVC cache and tracked by git (git rm --cached them, .gitignore them): {both}"


def test_compiled_caches_beside_the_code_are_no_dependency():
    """Python's .pyc and numba's cached kernels (plad/metrics/__pycache__) are written beside the code on first
    use: were they part of a folder's hash, every stage depending on plad/metrics would be stale after a run."""
    from dvc.repo import Repo

    with Repo(str(REPO)) as repo:
        ignored = [repo.dvcignore.is_ignored(repo.fs, str(REPO / p)) for p in (
            "plad/metrics/__pycache__/chamfer_compiled._canny-1.py311.nbi", "plad/__pycache__/layout.cpython-311.pyc",
            "plad/metrics/chamfer_compiled.py", "plad/metrics/chamfer.py")]
    assert ignored == [True, True, False, False]
