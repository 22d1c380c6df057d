"""The results record: one JSON file per benchmark table in ``benchmarks/results/``, the one source of
``docs/BENCHMARKS.md`` (``python benchmarks/bench.py report``).

Schema (``"schema": 1``), every key present:

``title``
    the section heading on the page (short, no commit hash).
``what``
    what the table measures and how (a few sentences; no history).
``command``
    the command that writes the record, run from the repository root; paths relative to it or under
    ``$GAUSEM_SHARED_DATA``, never absolute.
``machine``
    where it ran (CPU model and cores, GPU), or ``"unknown"``.
``commit``
    the git commit of the code that ran (``-dirty`` when the tree was modified), or ``"unknown"``.
``date``
    UTC date/time of the run (ISO 8601) or ``null`` when not known.
``table``
    ``{"title": str | null, "columns": [str, ...], "rows": [[cell, ...], ...]}``; cells are strings or numbers, one
    per column.

Optional keys: ``tables`` (further tables, same shape), ``notes`` (lines printed under the tables: per-row details
the script writes), ``reading`` (at most a few sentences on what the table shows, written by a person; kept when the
script rewrites the record, and then worth re-reading), ``data`` (the script's raw output: anything JSON).

Scripts write records through :func:`write` (which fills in ``command``, ``machine``, ``commit`` and ``date`` of the
current process unless given) and read them through :func:`read`; :func:`validate` names every problem.
"""
from __future__ import annotations

import json
import os
import platform
import re
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

SCHEMA = 1
ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"
REQUIRED = ("schema", "title", "what", "command", "machine", "commit", "date", "table")
OPTIONAL = ("tables", "notes", "reading", "data")
UNKNOWN = "unknown"
# a commit hash as prose would cite one (7-40 hex digits, a letter and a digit among them): only the commit field may
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
NOW = object()  # record()'s date: the current time
# a git commit as the page may show it (only in the record's commit field)
COMMIT = re.compile(r"^(unknown|[0-9a-f]{7,40}(-dirty)?( \([^()]*\))?(, [0-9a-f]{7,40}(-dirty)?( \([^()]*\))?)*)$")


# --- tables ---------------------------------------------------------------------------------------------------------
def table(columns, rows, title: str | None = None) -> dict:
    """A table: ``columns`` (names) and ``rows`` (sequences of cells, one per column)."""
    return {"title": title, "columns": [str(c) for c in columns], "rows": [list(r) for r in rows]}


def _cells(line: str) -> list[str]:
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def markdown_tables(text: str) -> list[dict]:
    """Every Markdown table of ``text``, each titled by the nearest heading or italic line above it."""
    tables, title, lines = [], None, text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if line.startswith("#"):
            title = line.lstrip("#").strip()
        elif re.fullmatch(r"\*[^*].*\*", line):
            title = line.strip("*").strip()
        elif line.startswith("|") and i + 1 < len(lines) and re.fullmatch(r"\|?[\s:|-]+\|?", lines[i + 1].strip()):
            columns, rows, i = _cells(line), [], i + 2
            while i < len(lines) and lines[i].strip().startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            tables.append(table(columns, rows, title))
            title = None
            continue
        i += 1
    return tables


def markdown_table(t: dict) -> str:
    """``t`` as a Markdown table."""
    def cell(value) -> str:
        return "–" if value is None else str(value).replace("|", "\\|").replace("\n", " ")
    lines = ["| " + " | ".join(cell(c) for c in t["columns"]) + " |", "|" + "---|" * len(t["columns"])]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in t["rows"]]
    return "\n".join(lines)


# --- where and what ran ---------------------------------------------------------------------------------------------
_ABSOLUTE = [(re.compile(r"(?:\.\.|(?<![\w.])(?:/[\w.-]+)+)/shared/data\b"), "$GAUSEM_SHARED_DATA"),
             (re.compile(r"(?<![\w.-])/(?:work|home|Users)/[\w.-]+/(?:[\w.-]+/)*?"
                         r"(?=(?:params|benchmarks|out|test|gausem_core)/)"), ""),
             (re.compile(r"(?<![\w.-])/(?:work|home|Users)/[\w.-]+/"), "")]


def relative(value):
    """``value`` (a string, or JSON made of them) with this machine's absolute paths made relative: the shared data
    folder as ``$GAUSEM_SHARED_DATA``, the repository's own files relative to its root."""
    if isinstance(value, str):
        value = value.replace(str(ROOT) + "/", "")
        for pattern, replacement in _ABSOLUTE:
            value = pattern.sub(replacement, value)
        return value
    if isinstance(value, list):
        return [relative(v) for v in value]
    if isinstance(value, dict):
        return {k: relative(v) for k, v in value.items()}
    return value


def current_command(argv: list[str] | None = None) -> str:
    """This process's command line as run from the repository root, with ``OMP_NUM_THREADS`` when set."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0])
    if script.is_absolute() and ROOT in script.parents:
        script = script.relative_to(ROOT)
    words = ["python", str(script), *argv[1:]]
    prefix = f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']} " if "OMP_NUM_THREADS" in os.environ else ""
    return relative(prefix + shlex.join(words))


def current_machine() -> str:
    """The CPU model and its cores, and the GPU when torch sees one."""
    try:
        match = re.search(r"model name\s*:\s*(.+)", Path("/proc/cpuinfo").read_text())
        cpu = match.group(1).strip() if match else platform.processor() or platform.machine()
    except OSError:
        cpu = platform.processor() or platform.machine()
    gpu = "no GPU"
    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        if torch.cuda.is_available():
            gpu = torch.cuda.get_device_name(0)
    return f"{cpu}, {os.cpu_count()} cores, {gpu}"


def current_commit() -> str:
    """HEAD's commit, ``-dirty`` when tracked files other than the records (what benchmarks write, one after
    another) differ from it; ``unknown`` outside a checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                f":(exclude){RESULTS.relative_to(ROOT)}"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return UNKNOWN
    return head + ("-dirty" if dirty else "")


def now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# --- records --------------------------------------------------------------------------------------------------------
def record(*, title: str, what: str, table: dict, tables=(), notes=(), reading: str | None = None,
           command: str | None = None, machine: str | None = None, commit: str | None = None,
           date=NOW, data=None) -> dict:
    """A record; ``command``, ``machine``, ``commit`` and ``date`` default to this process's (``date=None``: not
    known)."""
    doc = {"schema": SCHEMA, "title": title, "what": what,
           "command": relative(command if command is not None else current_command()),
           "machine": machine if machine is not None else current_machine(),
           "commit": commit if commit is not None else current_commit(),
           "date": now() if date is NOW else date, "table": table}
    if tables:
        doc["tables"] = list(tables)
    if notes:
        doc["notes"] = list(notes)
    if reading:
        doc["reading"] = reading
    if data is not None:
        doc["data"] = relative(data)
    return doc


def validate(doc) -> list[str]:
    """Every way ``doc`` departs from the schema (empty when it is a record)."""
    if not isinstance(doc, dict):
        return [f"a record is a JSON object, not {type(doc).__name__}"]
    problems = [f"missing {key!r}" for key in REQUIRED if key not in doc]
    problems += [f"unknown key {key!r}" for key in doc if key not in REQUIRED + OPTIONAL]
    if doc.get("schema") != SCHEMA:
        problems.append(f"schema is {doc.get('schema')!r}, expected {SCHEMA}")
    for key in ("title", "what", "command", "machine", "commit"):
        if key in doc and not (isinstance(doc[key], str) and doc[key].strip()):
            problems.append(f"{key!r} must be a non-empty string")
    if isinstance(doc.get("commit"), str) and not COMMIT.match(doc["commit"]):
        problems.append(f"commit {doc['commit']!r} is neither hex commits (with an optional '(what)') nor 'unknown'")
    if doc.get("date") is not None and not isinstance(doc.get("date"), str):
        problems.append("'date' must be a string or null")
    for where, t in [("table", doc.get("table"))] + [(f"tables[{i}]", t) for i, t in enumerate(doc.get("tables", []))]:
        if t is None and where == "table" and "table" not in doc:
            continue
        if not (isinstance(t, dict) and isinstance(t.get("columns"), list) and isinstance(t.get("rows"), list)):
            problems.append(f"{where} must have 'columns' and 'rows'")
            continue
        problems += [f"{where} row {i} has {len(r)} cells for {len(t['columns'])} columns"
                     for i, r in enumerate(t["rows"]) if not isinstance(r, list) or len(r) != len(t["columns"])]
    if "notes" in doc and not all(isinstance(n, str) for n in doc["notes"]):
        problems.append("'notes' must be strings")
    if "reading" in doc and not isinstance(doc["reading"], str):
        problems.append("'reading' must be a string")
    shown = [doc.get(k) for k in ("title", "what", "reading")] + list(doc.get("notes", []))
    for t in [doc.get("table") or {}, *doc.get("tables", [])]:
        shown += [t.get("title")] + [c for row in t.get("rows", []) for c in row]
    hashes = sorted({h for s in shown if isinstance(s, str) for h in HASH.findall(s)})
    if hashes:
        problems.append(f"commit hashes outside the commit field (the page shows no others): {', '.join(hashes)}")
    text = json.dumps(doc, default=_plain)
    if re.search(r"(?<![\w$.-])/(?:work|home|Users)/", text):
        problems.append("an absolute path of a machine (under work, home or Users)")
    return problems


def _plain(value):
    """numpy scalars and arrays, tuples of them, paths: as JSON has them."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return float(value)


class RecordError(ValueError):
    pass


def write(path: Path | str, doc: dict) -> Path:
    """Validate ``doc`` and write it to ``path`` (``.json`` added when missing). A ``reading`` already recorded at
    ``path`` is kept when ``doc`` has none (printed, to re-read against the new figures)."""
    path = Path(path)
    path = path if path.suffix == ".json" else path.with_name(path.name + ".json")
    if "reading" not in doc and path.is_file():
        try:
            old = json.loads(path.read_text()).get("reading")
        except (ValueError, AttributeError):
            old = None
        if old:
            doc = {**doc, "reading": old}
            print(f"{path}: kept the recorded reading; check it against the new table:\n  {old}", file=sys.stderr)
    problems = validate(doc)
    if problems:
        raise RecordError(f"{path}: " + "; ".join(problems))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False, default=_plain) + "\n")
    print(f"wrote {path} (python benchmarks/bench.py report writes docs/BENCHMARKS.md from it)")
    return path


def read(path: Path | str) -> dict:
    """The record at ``path``; :class:`RecordError` naming every problem when it is not one."""
    path = Path(path)
    doc = json.loads(path.read_text())
    problems = validate(doc)
    if problems:
        raise RecordError(f"{path}: " + "; ".join(problems))
    return doc


def all_records(folder: Path = RESULTS) -> dict[str, dict]:
    """Every record of ``folder`` by file stem, sorted."""
    return {p.stem: read(p) for p in sorted(Path(folder).glob("*.json"))}


def write_report(path: Path | str, *, title: str, what: str, markdown: str, notes=(), data=None, **fields) -> Path:
    """Write the record of a script that renders its results as Markdown (and print that Markdown): the Markdown's
    tables become the record's ``table`` and ``tables``; headings and other lines are left out (put what matters in
    ``what`` or ``notes``). ``fields``: :func:`record`'s ``reading``, ``command``, ``machine``, ``commit``, ``date``."""
    tables = markdown_tables(markdown)
    if not tables:
        raise RecordError(f"{path}: the report has no table")
    print(markdown)
    return write(path, record(title=title, what=what, table=tables[0], tables=tables[1:], notes=notes, data=data,
                              **fields))


def label(spec: str) -> str:
    """A dataset spec as a section title names it: ``synthetic:loop`` -> ``synthetic loop``, ``tum:PATH/tum_fr1_rpy``
    -> ``tum_fr1_rpy``."""
    kind, _, rest = spec.partition(":")
    return f"{kind} {rest}".strip() if kind == "synthetic" else Path(rest or kind).name
