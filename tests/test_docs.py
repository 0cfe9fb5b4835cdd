"""The documentation keeps its promises: the README's quick start runs, every public module is in the API
reference, and the user pages (everything outside docs/research/) read as a guide: no dates, issue numbers
or commit hashes, at most 400 lines each."""
from __future__ import annotations

import pkgutil
import re
from pathlib import Path

import pytest

import torch_hsh

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MAX_LINES = 400


def user_pages():
    """README.md, CONTRIBUTING.md and every markdown page of the site outside docs/research/ and generated
    folders."""
    pages = [ROOT / "README.md", ROOT / "CONTRIBUTING.md"]
    for p in sorted(DOCS.rglob("*.md")):
        rel = p.relative_to(DOCS).parts
        if rel[0] in ("research", "_build", "gallery"):
            continue
        pages.append(p)
    return pages


def fenced_block(text: str, heading: str, lang: str = "python") -> str:
    """The ```lang block that directly follows ``heading`` (a markdown heading line; blank lines between)."""
    m = re.search(rf"^{re.escape(heading)}\s*\n\s*```{lang}\n(.*?)^```", text, re.M | re.S)
    assert m, f"no ```{lang} block directly under {heading!r}"
    return m.group(1)


def test_readme_quick_start_runs():
    code = fenced_block((ROOT / "README.md").read_text(encoding="utf-8"), "## Quick start")
    namespace: dict = {}
    exec(compile(code, "README.md quick start", "exec"), namespace)  # noqa: S102 - the README's own code
    assert tuple(namespace["rgb"].shape) == (2048, 3)
    assert tuple(namespace["B"].shape) == (2048, torch_hsh.num_isotropic(4))


def test_site_quick_start_is_the_readmes():
    readme = fenced_block((ROOT / "README.md").read_text(encoding="utf-8"), "## Quick start")
    site = fenced_block((DOCS / "index.md").read_text(encoding="utf-8"), "## Quick start")
    assert site == readme


def test_every_public_module_is_in_the_api_reference():
    api = "".join((DOCS / name).read_text(encoding="utf-8") for name in ("api.md", "api_applications.md"))
    documented = set(re.findall(r"^\.\. automodule:: (\S+)\s*$", api, re.M))
    public = {m.name for m in pkgutil.walk_packages(torch_hsh.__path__, "torch_hsh.")
              if not any(part.startswith("_") for part in m.name.split("."))}
    assert public - documented == set(), "add these modules to docs/api.md or docs/api_applications.md"
    assert documented - public == set(), "docs/api*.md name modules that do not exist"


def test_every_subpackage_is_an_attribute_after_import():
    import subprocess
    import sys

    subs = sorted({m.name.split(".")[1] for m in pkgutil.iter_modules(torch_hsh.__path__, "torch_hsh.")
                   if not m.name.split(".")[1].startswith("_")})
    code = "import torch_hsh\n" + "".join(f"torch_hsh.{s}\n" for s in subs)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


_DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
_ISSUE = re.compile(r"\bissues?[ -]?#?\d+\b", re.I)
_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b")


@pytest.mark.parametrize("page", user_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_user_page_reads_as_a_guide(page):
    text = page.read_text(encoding="utf-8")
    lines = text.splitlines()
    assert len(lines) <= MAX_LINES, f"{page.name}: {len(lines)} lines (at most {MAX_LINES}; history goes to docs/research/)"
    for pattern, what in ((_DATE, "a date"), (_ISSUE, "an issue number"), (_HASH, "a commit hash")):
        found = [f"{k + 1}: {ln.strip()}" for k, ln in enumerate(lines) if pattern.search(ln)]
        assert not found, f"{page.name} holds {what} (research notes go to docs/research/):\n" + "\n".join(found[:5])


def test_checks_catch_what_they_should():
    assert _DATE.search("measured 2026-12-03, afternoon")
    assert _ISSUE.search("the issue-21 suite") and _ISSUE.search("see issue 8")
    assert _HASH.search("commit 6d85856") and not _HASH.search("1234567 pixels") and not _HASH.search("deadbeef")


def test_project_files_exist():
    for name in ("CHANGELOG.md", "CITATION.cff", "CONTRIBUTING.md", "LICENSE"):
        assert (ROOT / name).is_file(), name
    cff = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert "cff-version: 1.2.0" in cff and "Elhabian" in cff


def test_citation_and_changelog_name_the_package_version():
    import torch_hsh
    cff = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert f"\nversion: {torch_hsh.__version__}\n" in cff
    release = torch_hsh.__version__.split(".dev")[0]
    assert f"## {release}" in (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")


def _doc_commands():
    """Every ``torch-hsh ...`` line of a ```bash block of a user page, as (page, line)."""
    for page in user_pages():
        for block in re.findall(r"^```bash\n(.*?)^```", page.read_text(encoding="utf-8"), re.M | re.S):
            for line in block.splitlines():
                if line.startswith("torch-hsh "):
                    yield page.relative_to(ROOT).as_posix(), line


def test_the_documented_commands_parse(capsys):
    """A command that a page shows is one the parser takes (options spelled as they are, required ones given)."""
    import shlex

    from torch_hsh.cli import build_parser

    commands = list(_doc_commands())
    assert len(commands) > 10
    for page, line in commands:
        argv = shlex.split(line, comments=True)[1:]
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            pytest.fail(f"{page}: `{line}` does not parse: {capsys.readouterr().err.strip().splitlines()[-1]}")
