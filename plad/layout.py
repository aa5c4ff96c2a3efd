"""Where the pipeline's artifacts live: the one home of every artifact path.

Stages, flows and the report derive their files from a :class:`Layout` (a
root, by default the working directory, plus the domain and method); params
hold no paths. ``dvc.yaml`` has to spell the same paths literally, and
``tests/pipeline/test_dvc_deps.py`` checks that it does::

    data/prepared/<domain>.npz, <domain>.json    real target shapes (stage prepare; plus each
                                                 target source's own files, e.g. partnet_voxels.npz)
    data/synthetic/<domain>.npz, <domain>.json   synthetic pretraining programs (synthesize@<domain>)
    data/labels/<domain>.npz, <domain>.json      search labels of the real training shapes (label@<domain>;
                                                 resumable chunks in <domain>.parts/)
    runs/pretrain/<domain>/                      pretraining: best.pt, last.pt, history.csv, summary.json
    runs/finetune/<domain>/<method>/             fine-tuning: best.pt, state.json, summary.json, method state
    results/finetune/<domain>/<method>.json      the fine-tuning summary again, as a DVC metric
    results/eval/<method>/<domain>/              test evaluation: metrics.json, <split>_programs.csv, grid.png
    results/eval/<method>_refined/<domain>/      the same with test-time refinement of the beam's outputs
    results/eval/<method>_beam<k>/<domain>/      the same with beam k (the amortization sweep)
    results/eval/search/<domain>/                search from scratch, no network (stage search_only)
    results/eval/floor/<domain>/                 the floor baseline (with SP's evaluation): metrics.json,
                                                 <split>_programs.csv
    results/table.md, convergence.png, report.json   the report
    results/amortization.md, amortization.png    the report: metric against seconds per shape
    runs/flows/<run name>/                       a Prefect flow run: the same layout below it

The pretrained model is the method ``sp`` (:data:`SP`): its model is
``runs/pretrain/<domain>/best.pt``, its evaluation ``results/eval/sp/<domain>/``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: the method key of the pretrained (supervised) model, the first row of the results table
SP = "sp"
#: the key of the domain's floor baseline (:meth:`plad.domains.base.Domain.floor`), evaluated with SP:
#: ``results/eval/floor/<domain>/``
FLOOR = "floor"

# file names inside a run folder, shared by the training loops that write them and the stages that read them
BEST = "best.pt"          # the selected model
LAST = "last.pt"          # pretraining's resume state
STATE = "state.json"      # a fine-tuning run's loop state and history
SUMMARY = "summary.json"  # a run's summary
HISTORY = "history.csv"   # pretraining's per-epoch metrics
PROVENANCE = "provenance.json"  # a pretraining's segments (what its checkpoint holds)
# file names of a test evaluation and of the report
METRICS = "metrics.json"
GRID = "grid.png"
TABLE = "table.md"
CONVERGENCE = "convergence.png"
REPORT = "report.json"
AMORTIZATION_TABLE = "amortization.md"
AMORTIZATION_PLOT = "amortization.png"
#: the result key (``results/eval/search/<domain>/``) of search from scratch without a network
SEARCH = "search"


def eval_key(method: str, beam: int | None = None, refine: bool = False, effort: str | None = None) -> str:
    """The result key of an evaluation: the method's, ``<method>_beam<k>`` for a beam of the amortization
    sweep, ``<method>_refined`` with test-time refinement (``refine_config``), ``<method>_refined_<effort>``
    with the refinement of an effort level (``plad infer --effort``)."""
    return (method + (f"_beam{beam}" if beam is not None else "") + ("_refined" if refine or effort else "")
            + (f"_{effort}" if effort else ""))


#: the effort levels that name result keys (:data:`plad.rewrite.EFFORTS`, which a test holds equal; not imported:
#: the layout stays free of torch)
EFFORT_LEVELS = ("fast", "default", "best")


def split_effort(key: str) -> tuple[str, str | None]:
    """(the key without its effort level, the level or None): ``search_best`` -> (``search``, ``best``),
    ``m_refined_fast`` -> (``m_refined``, ``fast``), ``search`` -> (``search``, None)."""
    head, _, level = key.rpartition("_")
    if level in EFFORT_LEVELS and (head == SEARCH or head.endswith("_refined")):
        return head, level
    return key, None


def search_key(effort: str = "default") -> str:
    """The result key of search from scratch at an effort level: ``search`` at ``default`` (the table's row),
    ``search_<effort>`` at the others."""
    return SEARCH if effort == "default" else f"{SEARCH}_{effort}"


def programs_csv(split: str) -> str:
    """The per-shape programs of an evaluated split: ``<split>_programs.csv``."""
    return f"{split}_programs.csv"


@dataclass(frozen=True)
class Layout:
    """Artifact paths under ``root``.

    ``upstream`` is where a run that starts from an existing pipeline reads
    the prepared data, the synthetic programs and the pretrained models (a
    Prefect flow run retrains from the project's, see :meth:`flow_run`);
    ``None``: the same root.
    """

    root: Path = Path(".")
    upstream: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        if self.upstream is not None:
            object.__setattr__(self, "upstream", Path(self.upstream))

    @property
    def _start(self) -> Path:
        return self.root if self.upstream is None else self.upstream

    # -- data -------------------------------------------------------------------------------------
    @property
    def prepared_dir(self) -> Path:
        return self._start / "data" / "prepared"

    def prepared(self, domain: str) -> Path:
        return self.prepared_dir / f"{domain}.npz"

    def prepared_summary(self, domain: str) -> Path:
        return self.prepared_dir / f"{domain}.json"

    @property
    def synthetic_dir(self) -> Path:
        return self._start / "data" / "synthetic"

    def synthetic(self, domain: str) -> Path:
        return self.synthetic_dir / f"{domain}.npz"

    def synthetic_summary(self, domain: str) -> Path:
        return self.synthetic_dir / f"{domain}.json"

    @property
    def labels_dir(self) -> Path:
        """Search labels of the real training shapes (stage ``label@<domain>``): ``<domain>.npz``, ``.json``."""
        return self._start / "data" / "labels"

    def labels(self, domain: str) -> Path:
        return self.labels_dir / f"{domain}.npz"

    # -- training runs ----------------------------------------------------------------------------
    def pretrain_dir(self, domain: str) -> Path:
        return self._start / "runs" / "pretrain" / domain

    def finetune_dir(self, domain: str, method: str) -> Path:
        return self.root / "runs" / "finetune" / domain / method

    def finetune_summary(self, domain: str, method: str) -> Path:
        return self.root / "results" / "finetune" / domain / f"{method}.json"

    def model(self, domain: str, method: str = SP) -> Path:
        """The selected model of a method: pretraining's for :data:`SP`, else the fine-tuning run's."""
        return (self.pretrain_dir(domain) if method == SP else self.finetune_dir(domain, method)) / BEST

    # -- results ----------------------------------------------------------------------------------
    def eval_dir(self, method: str, domain: str) -> Path:
        return self.root / "results" / "eval" / method / domain

    @property
    def results_dir(self) -> Path:
        """The report's folder: :data:`TABLE`, :data:`CONVERGENCE`, :data:`REPORT`."""
        return self.root / "results"

    # -- flow runs --------------------------------------------------------------------------------
    def flow_run(self, name: str) -> Layout:
        """The layout of a Prefect flow run: its outputs under ``runs/flows/<name>/``, its start here."""
        return Layout(self.root / "runs" / "flows" / name, upstream=self._start)
