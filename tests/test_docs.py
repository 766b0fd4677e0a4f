"""The documentation stays true: the site builds strictly, its Python snippets run, and it speaks only of the project.

* ``mkdocs build --strict`` (mkdocs.yml: no broken link or anchor, no page left out of the navigation).
* The ```python blocks of README.md and docs/*.md run, each file's blocks in order in one namespace, in a temporary
  working folder. A block preceded by ``<!-- no-run -->`` is skipped (e.g. a script that needs its own main module).
* No file under ``HISTORY_GUARD_ROOTS`` tells how the project was developed: numbered work periods, tracker numbers,
  commit hashes, remarks about the build machine, or dates (but a changelog's release headings and the benchmark
  page's measurement line).
"""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# the files and folders the history guard scans (relative to the repository root): the whole tree
HISTORY_GUARD_ROOTS = (".",)

HISTORY_PATTERNS = {
    "numbered work period": re.compile(r"\bsessions? \d+", re.IGNORECASE),
    "tracker number": re.compile(r"\b(?:issues?|PR) #?\d+", re.IGNORECASE),
    "helper number": re.compile(r"\bhelper-\d+", re.IGNORECASE),
    "remark about the build machine": re.compile(r"\bthis VM\b", re.IGNORECASE),
    # a hexadecimal word with a letter and a digit, after words that introduce a revision
    "commit hash": re.compile(r"\b(?:commit|at|code) (?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,12}\b"),
    "date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
}
# lines where a date belongs: a changelog's release headings, the benchmark page's measurement line
DATE_LINES = {"CHANGELOG.md": re.compile(r"^## \["), "docs/benchmarks.md": re.compile(r"^Measured on ")}

NO_RUN = "<!-- no-run -->"
_BLOCK = re.compile(r"^```python[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)


def python_blocks(text: str) -> list[str]:
    """The ```python blocks of a markdown text, without those marked ``<!-- no-run -->`` on the line before."""
    blocks = []
    for m in _BLOCK.finditer(text):
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1].strip()
        if before != NO_RUN:
            blocks.append(m.group(1))
    return blocks


def history_findings(relpath: str, text: str) -> list[str]:
    """'path:line: what (the matched text)' for every mention of the project's development in ``text``."""
    found = []
    date_line = DATE_LINES.get(relpath)
    for number, line in enumerate(text.splitlines(), 1):
        for what, pattern in HISTORY_PATTERNS.items():
            if what == "date" and date_line is not None and date_line.search(line):
                continue
            for m in pattern.finditer(line):
                found.append(f"{relpath}:{number}: {what} ({m.group(0)!r})")
    return found


def guarded_files() -> list[Path]:
    """Files under HISTORY_GUARD_ROOTS: git's tracked and untracked (not ignored) ones, else every file outside
    hidden folders and build products."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "--",
                              *HISTORY_GUARD_ROOTS], cwd=ROOT, capture_output=True, text=True, check=True).stdout
        files = [ROOT / line for line in out.splitlines() if line]
    except (OSError, subprocess.CalledProcessError):
        files = []
        for root in HISTORY_GUARD_ROOTS:
            path = ROOT / root
            files += [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
        # without git: leave out hidden folders (.git, .venv) and build products
        files = [f for f in files if not any(part.startswith(".") or part.endswith(".egg-info")
                                             for part in f.relative_to(ROOT).parts[:-1])]
    return [f for f in files if f.is_file() and "__pycache__" not in f.parts]


def _snippet_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
    return [f for f in files if python_blocks(f.read_text(encoding="utf-8"))]


def test_mkdocs_build_strict(tmp_path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[docs]')")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                           str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
                          cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "changelog" / "index.html").read_text(encoding="utf-8").count("0.2.0") >= 1


def test_every_docs_page_is_in_the_navigation():
    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    _Loader.add_multi_constructor("!", lambda loader, suffix, node: None)  # mkdocs' !relative and the like
    config = yaml.load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"), Loader=_Loader)
    listed = {next(iter(entry.values())) for entry in config["nav"]}
    assert listed == {p.name for p in DOCS.glob("*.md")}


@pytest.mark.parametrize("path", _snippet_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_python_snippets_run(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    for i, block in enumerate(python_blocks(path.read_text(encoding="utf-8")), 1):
        code = compile(block, f"{path.relative_to(ROOT).as_posix()} (python block {i})", "exec")
        exec(code, namespace)


def test_command_line_page_lists_every_command_and_option():
    import argparse

    from ti_cmax.cli import COMMANDS, build_parser

    page = (DOCS / "command-line.md").read_text(encoding="utf-8")
    sections = dict(re.findall(r"^## ([a-z-]+)\n(.*?)(?=^## |\Z)", page, re.MULTILINE | re.DOTALL))
    common = {"--config", "--set", "--threads", "--quiet", "-h", "--help"}
    for name in COMMANDS:
        assert name in sections, f"command-line.md has no section for {name}"
        parser = build_parser(name)
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
        for action in sub._actions:
            for option in set(action.option_strings) - common:
                assert f"`{option}" in sections[name], f"command-line.md, {name}: {option} is missing"
    for option in common - {"-h", "--help"}:
        assert f"`{option}" in page


def test_every_docs_picture_is_shown():
    """Each picture under docs/img is shown by a page (or the README), and the live viewer's picture is there."""
    pages = "".join(p.read_text(encoding="utf-8") for p in [ROOT / "README.md", *DOCS.glob("*.md")])
    pictures = sorted(p.name for p in (DOCS / "img").iterdir())
    assert "viewer.png" in pictures and "demo.png" in pictures
    for name in pictures:
        assert f"img/{name})" in pages, f"docs/img/{name} is shown nowhere"
    assert "(img/viewer.png)" in (DOCS / "getting-started.md").read_text(encoding="utf-8")


def test_readme_is_a_front_page():
    """The README says what and why, how to install and run, and links into docs/; the rest lives in docs/."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    linked = set(re.findall(r"\(docs/([a-z-]+\.md)", readme))
    assert linked <= {p.name for p in DOCS.glob("*.md")}, linked - {p.name for p in DOCS.glob("*.md")}


def test_snippet_extraction_skips_marked_blocks():
    text = "a\n```python\nx = 1\n```\n<!-- no-run -->\n```python\nraise SystemExit\n```\n```python\ny = 2\n```\n"
    assert python_blocks(text) == ["x = 1\n", "y = 2\n"]


def test_history_patterns_catch_development_remarks():
    # the samples are assembled at run time, so this file itself passes the guard when it scans the tests
    n, day, rev = 12, "12-02", "4f78af1"
    bad = [f"measured in session {n}", f"see issue #{n}", f"by helper-{n}", f"slow on this {'VM'}", f"fixed at {rev}",
           f"since commit {rev}", f"on {2026}-{day} the suite", f"Issue {n} is blocked"]
    for line in bad:
        assert history_findings("docs/x.md", line), line
    good = ["at 1000000 events", "a 2048x1024 map", "the issues page", "## [0.2.0] - unreleased",
            "0.1 s sessions of data", "code 2 on bad input"]
    for line in good:
        assert not history_findings("docs/x.md", line), line
    assert not history_findings("CHANGELOG.md", f"## [0.1.0] - {2026}-{day}")
    assert history_findings("CHANGELOG.md", f"- fixed on {2026}-{day}")
    assert not history_findings("docs/benchmarks.md", f"Measured on {2026}-{day}, 2 cores")


def test_docs_do_not_tell_the_development_history():
    findings = [f for path in guarded_files()
                for f in history_findings(path.relative_to(ROOT).as_posix(), path.read_text(encoding="utf-8",
                                                                                          errors="replace"))]
    assert not findings, "\n".join(findings)
