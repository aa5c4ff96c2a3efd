"""The results table lays out what each domain declares: display name, scale, digits and the paper's numbers."""
from plad.domains import domain_names, get_domain
from plad.eval.report import MethodResult, table_markdown


def test_table_shows_each_domain_as_it_declares_itself():
    results = {name: [MethodResult("sp", 0.5), MethodResult("lest_st", 0.25),
                      MethodResult("lest_st_per_round", None)] for name in domain_names()}
    text = table_markdown(results, ["sp", "lest_st"], {"lest_st": "lest_st_per_round"}, profile="cpu")
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("| method |"))
    row = next(line for line in lines if line.startswith("| SP |")).split("|")[2:-1]
    for i, name in enumerate(domain_names()):
        d = get_domain(name)
        assert f"{d.display_name}: {d.metric.name}" in header
        ours, paper = row[2 * i].strip(), row[2 * i + 1].strip()
        assert ours == f"{0.5 * d.display_scale:.{d.display_digits}f}"
        want = d.paper_table.get("sp")
        assert paper == ("—" if want is None else f"{want:.{d.display_digits}f}")
        # the supplement's per-round numbers, where the domain declares them
        block = lines[lines.index(f"{d.display_name}:") + 4].split("|")[1:-1]
        assert block[0].strip() == "LEST+ST" and block[1].strip() == f"{0.25 * d.display_scale:.{d.display_digits}f}"
        want = d.paper_per_round.get("lest_st")
        assert block[4].strip() == ("—" if want is None else f"{want:.{d.display_digits}f}")
