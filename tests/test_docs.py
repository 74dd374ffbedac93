"""The documentation stays usable: a short README whose example runs, links that resolve, a glossary that
defines the words the README uses, and reference text that describes the project rather than how it was built
(history belongs in CHANGELOG.md)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
README = ROOT / "README.md"
GLOSSARY = ROOT / "docs" / "index.md"

# Text that narrates the project's making: the same pattern the developers' guide greps for.
NOTEBOOK = re.compile(r"session [0-9]|issue #?[0-9]|\bthe issue(?:'s)?\b", re.IGNORECASE)
SKIPPED_DIRS = {"node_modules", "build", "dist", "var", "__pycache__"}  # and every dot-directory (.venv, .git)

# The project's own vocabulary: every one of these the README uses must have a glossary entry.
JARGON = [
    "action", "adapter", "Algorithm 1", "API key", "assumed rule", "behaviour cloning", "cache hit",
    "candidate", "cautious ranking", "check", "code model", "constrained mode", "demonstration", "enumerator",
    "established rule", "evidence", "event", "fork server", "gateway", "guard", "history", "job",
    "model-free", "next action", "observation", "policy", "precondition", "precondition set", "prior rules",
    "program", "queue", "ranking", "review page", "rule", "sandbox", "spec", "tenant", "thin evidence",
    "tolerance", "tool call", "validation", "verdict", "version", "warm child", "worker", "zero-shot rule",
]


def _links(path: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    return re.findall(r"\]\(([^)\s]+)\)", text)


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces as hyphens."""
    anchors = set()
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def _glossary_terms() -> set[str]:
    text = GLOSSARY.read_text(encoding="utf-8").split("## Glossary", 1)[1]
    terms = set()
    for head in re.findall(r"^\*\*(.+?)\*\*(?:\s*\(([^)]*)\))?", text, flags=re.MULTILINE):
        for part in re.split(r",\s*|\*\*", head[0]):
            terms.add(re.sub(r"\s*\(.*", "", part).strip().lower())
    return {term for term in terms if term}


def test_readme_is_at_most_200_lines() -> None:
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 200


def test_every_relative_link_in_readme_and_docs_resolves() -> None:
    broken = []
    for page in [README, *DOCS]:
        for link in _links(page):
            if re.match(r"[a-z]+:", link):
                continue  # http(s), mailto: not ours to check offline
            target, _, anchor = link.partition("#")
            path = (page.parent / target).resolve() if target else page
            if not path.exists():
                broken.append(f"{page.relative_to(ROOT)}: {link} (no such file)")
            elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
                broken.append(f"{page.relative_to(ROOT)}: {link} (no such heading)")
    assert not broken, "\n".join(broken)


def _project_files() -> list[Path]:
    """The project's Markdown and Python files: what a checkout holds, not what installing or running it made."""
    files = []
    for folder, dirs, names in os.walk(ROOT):
        dirs[:] = [name for name in dirs if name not in SKIPPED_DIRS and not name.startswith(".")]
        files += [Path(folder) / name for name in names if name.endswith((".md", ".py"))]
    return files


def test_nothing_in_the_project_narrates_sessions_or_issues() -> None:
    found = []
    for path in _project_files():
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if NOTEBOOK.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "\n".join(found)


def test_the_glossary_defines_every_project_term_the_readme_uses() -> None:
    readme = README.read_text(encoding="utf-8").lower()
    defined = _glossary_terms()
    missing = [term for term in JARGON
               if re.search(r"\b" + re.escape(term.lower()) + r"s?\b", readme) and term.lower() not in defined]
    assert not missing, f"used in README.md, not in the glossary of docs/index.md: {missing}"
    assert len(defined) >= len(JARGON) // 2  # the parse found the entries at all


def test_the_readme_example_runs_and_says_what_it_prints() -> None:
    """The README's Python example, run as written from the checkout: its printed lines are its comments."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.DOTALL)
    example = next(block for block in blocks if "build_engine" in block)
    expected = [re.search(r"#\s*(.+?)(?::.*)?$", line).group(1).strip()  # type: ignore[union-attr]
                for line in example.splitlines() if line.startswith("print(")]
    run = subprocess.run([sys.executable, "-c", example], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == expected


def test_the_readme_set_up_commands_exist_and_do_what_it_says() -> None:
    """`serve.sh` starts the service, `test.sh` installs and runs the tests: the README's two commands."""
    readme = README.read_text(encoding="utf-8")
    for script, does in (("serve.sh", "precond serve"), ("test.sh", "pytest")):
        path = ROOT / "scripts" / script
        assert f"./scripts/{script}" in readme
        assert os.access(path, os.X_OK), f"scripts/{script} is not executable"
        assert does in path.read_text(encoding="utf-8") and "./scripts/install.sh" in path.read_text(encoding="utf-8")


def test_every_section_the_project_cites_by_name_exists() -> None:
    """`docs/method.md: 'Prior rules'` in a docstring or an API description names a heading (or a paragraph's bold
    title) of that page."""
    cited = re.compile(r"((?:README|docs/[\w-]+)\.md|README)[:,] ['\"]([^'\"]+)['\"]")
    stale = []
    for path in _project_files():
        for page, section in cited.findall(path.read_text(encoding="utf-8", errors="replace")):
            target = ROOT / (page if page.endswith(".md") else "README.md")
            text = target.read_text(encoding="utf-8")
            headings = [line.lstrip("#").strip().lower() for line in text.splitlines() if line.startswith("#")]
            headings += [title.lower() for title in re.findall(r"^\*\*(.+?)\*\*", text, flags=re.MULTILINE)]
            if not any(section.lower() in heading for heading in headings):
                stale.append(f"{path.relative_to(ROOT)}: {page} '{section}'")
    assert not stale, "\n".join(stale)


def test_every_upper_case_page_the_project_cites_exists() -> None:
    """A page cited by its name alone (README.md, CHANGELOG.md) is a file of the checkout; a page of the data is
    cited with its folder (`tau-airline/LABELS.md`), so that a reader knows where to look."""
    names = {path.name for path in _project_files()}
    cited = re.compile(r"(?<![\w/.-])([A-Z][A-Z_]*\.md)\b")
    missing = [f"{path.relative_to(ROOT)}: {name}" for path in _project_files()
               for name in cited.findall(path.read_text(encoding="utf-8", errors="replace")) if name not in names]
    assert not missing, "\n".join(missing)
