"""The documentation stays honest: docs/BENCHMARKS.md is what ``python benchmarks/bench.py report`` writes from the
records, every relative link of README.md and docs/*.md points at a file (and heading) that exists, the prose cites
no commit hash, every results record follows the schema, and no file names an absolute path of a machine."""
import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from gausem_bench import report, results

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
# a commit as prose would cite it: 7-40 hex digits with at least one letter and one digit (a plain number is no hash)
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+)$", text, flags=re.M)}


def prose(page: Path) -> str:
    """The page's text a person wrote: for the generated page, without its ``Ran on ...`` lines (machine and commit
    of each record, the one place commits may appear)."""
    lines = page.read_text().splitlines()
    if page.name == "BENCHMARKS.md":
        lines = [line for line in lines if not line.startswith(report.RAN_ON)]
    return "\n".join(lines)


def test_the_results_page_is_what_the_report_writes():
    assert report.PAGE.read_text() == report.render_page(), \
        "docs/BENCHMARKS.md differs from the records: run python benchmarks/bench.py report"


def test_every_results_record_follows_the_schema():
    paths = sorted(results.RESULTS.glob("*.json"))
    assert paths
    assert {p.name: results.validate(__import__("json").loads(p.read_text())) for p in paths} == \
           {p.name: [] for p in paths}
    assert not list(results.RESULTS.glob("*.md")), "the results page is generated: no .md beside the records"


def test_every_record_names_only_scripts_and_files_the_repository_holds():
    """A record must be re-runnable from a checkout: the scripts, suites and parameter files its command names exist
    (a throw-away suite in a temporary folder does not)."""
    absent = {}
    for path in sorted(results.RESULTS.glob("*.json")):
        values = [token.split("=", 1)[-1] for token in shlex.split(json.loads(path.read_text())["command"])]
        missing = [v for v in values if v.endswith((".py", ".yaml", ".sh")) and not (ROOT / v).exists()]
        if missing:
            absent[path.name] = missing
    assert absent == {}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_point_at_files_and_headings_that_exist(page):
    dead = []
    for target in LINK.findall(re.sub(r"```.*?```", "", page.read_text(), flags=re.S)):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            dead.append(target)
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            dead.append(target)
    assert dead == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_prose_cites_no_commit_hash(page):
    assert HASH.findall(prose(page)) == []


def test_the_hash_rule_tells_hashes_from_numbers():
    assert HASH.findall("at 1dd1033, commit 04dc68041ebebedb14ce1c9b2d32befd2eba270f") == \
           ["1dd1033", "04dc68041ebebedb14ce1c9b2d32befd2eba270f"]
    assert HASH.findall("921600 pixels, 4799958 Gaussians, a decade, facade, 0.5x") == []


def test_no_file_names_an_absolute_path_of_a_machine():
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.splitlines()
    prefixes = tuple("/" + name + "/" for name in ("work", "home", "Users"))
    found = [name for name in files if (ROOT / name).is_file()
             and any(prefix in (ROOT / name).read_text(errors="ignore") for prefix in prefixes)]
    assert found == []


def test_a_script_report_becomes_a_record(tmp_path, capsys):
    markdown = "# heading\n\n*first*\n\n| a | b |\n|---|---|\n| 1 | x \\| y |\n\n## second\n\n| c |\n|---|\n| 2 |\n"
    path = results.write_report(tmp_path / "thing", title="A thing", what="What it measures.", markdown=markdown,
                                notes=["a note"], data={"params_file": "/" + "work/x/params/tum.yaml",
                                                        "dataset": "tum:" + "/" + "work/shared/data/tum_fr1_rpy"},
                                command="python benchmarks/thing.py", machine="m", commit="0123abc", date=None)
    doc = results.read(path)
    assert path.name == "thing.json" and doc["date"] is None and doc["notes"] == ["a note"]
    assert doc["table"] == {"title": "first", "columns": ["a", "b"], "rows": [["1", "x | y"]]}
    assert doc["tables"] == [{"title": "second", "columns": ["c"], "rows": [["2"]]}]
    assert doc["data"] == {"params_file": "params/tum.yaml", "dataset": "tum:$GAUSEM_SHARED_DATA/tum_fr1_rpy"}
    doc["reading"] = "Kept."
    path.write_text(__import__("json").dumps(doc))
    results.write(path, results.record(title="A thing", what="w", table=doc["table"], command="c", machine="m",
                                       commit="unknown", date=None))
    assert results.read(path)["reading"] == "Kept."
    assert results.validate({**doc, "commit": "last week"}) and results.validate({**doc, "table": {"columns": ["a"],
                                                                                                    "rows": [[1, 2]]}})


def test_the_readmes_figures_are_the_paper_suites():
    """The README's figures table quotes the paper suite's records: GauSem's ATE and fps of every row."""
    ate, fps = set(), set()
    for stem in ("slam_paper_a", "slam_paper_b"):
        doc = results.read(results.RESULTS / f"{stem}.json")
        for t in [doc["table"], *doc.get("tables", [])]:
            if t["title"].startswith("Tracking"):
                ate |= {c for row in t["rows"] if row[0] == "gausem" for c in row[2:]}
            if t["title"].startswith("Runtime"):
                fps |= {row[t["columns"].index("fps ↑")] for row in t["rows"] if row[1] == "gausem"}
    section = (ROOT / "README.md").read_text().split("## Current figures")[1].split("\n## ")[0]
    rows = [line.split("|")[1:-1] for line in section.splitlines() if line.startswith("| ") and " cm |" in line]
    assert len(rows) == 6
    assert {r[1].strip().removesuffix(" cm") for r in rows} <= ate
    assert {r[4].strip() for r in rows} <= fps
