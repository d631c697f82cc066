"""The docs cannot rot silently: every relative link, every ``#anchor`` and every repository path cited
in README.md, CHANGELOG.md and docs/ resolves, and every Python snippet of the README runs."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").rglob("*.md")])
DOCS = [path for path in DOCS if path.exists()]

LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s+(\S+)", re.M)  # a reference-style definition: [id]: path
CODE_SPAN = re.compile(r"`([^`\n]+)`")
# a path into the repository as docs cite it in code spans: `trakdis/envs/cloth_env.py`, `docs/tasks.md`, `tests/`
REPO_PATH = re.compile(r"^(?:\./)?((?:trakdis|recipes|benchmarks|tests|docs)/[\w./-]*)$")
FENCE = re.compile(r"^(```|~~~)")


def prose(text: str) -> str:
    """``text`` without its fenced code blocks (commands there are not links)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            fenced = not fenced
            continue
        out.append("" if fenced else line)
    return "\n".join(out)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    text = text.strip().lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor GitHub gives ``path``'s headings (a repeated heading gets ``-1``, ``-2``, ...)."""
    found, counts = set(), {}
    for line in prose(path.read_text()).splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            base = slug(match.group(1))
            found.add(f"{base}-{counts[base]}" if base in counts else base)
            counts[base] = counts.get(base, 0) + 1
    return found


def links(path: Path) -> list[str]:
    text = prose(path.read_text())
    return [target for target in LINK.findall(text) + REFERENCE.findall(text)
            if not re.match(r"^[a-z]+:", target)]  # https:, mailto: ... are not checked here


def cited_paths(path: Path) -> list[str]:
    paths = []
    for span in CODE_SPAN.findall(prose(path.read_text())):
        for word in span.split():
            match = REPO_PATH.match(word.rstrip(".,;:"))
            if match and not any(ch in match.group(1) for ch in "*<>{}"):  # patterns such as `runs/<name>/`
                paths.append(match.group(1))
    return paths


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve(doc):
    broken = []
    for target in links(doc):
        file, _, anchor = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor} in {dest.relative_to(ROOT)}")
    assert not broken, f"{doc.relative_to(ROOT)}: broken links:\n" + "\n".join(broken)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_cited_paths_exist(doc):
    missing = sorted({p for p in cited_paths(doc) if not (ROOT / p).exists()})
    assert not missing, f"{doc.relative_to(ROOT)} cites paths that do not exist: {missing}"


def test_slug_matches_github():
    assert slug("Why the student closes farther out (`distill.py`)") == "why-the-student-closes-farther-out-distillpy"
    assert slug("Table I: 3 tasks x 3 seeds, 100 trials") == "table-i-3-tasks-x-3-seeds-100-trials"


def test_checker_finds_a_broken_link(tmp_path):
    doc = tmp_path / "a.md"
    (tmp_path / "b.md").write_text("# Real heading\n")
    doc.write_text("[ok](b.md#real-heading) [bad](b.md#nowhere) [gone](c.md)\n```\n[not a link](d.md)\n```\n"
                   "![img][ref]\n\n[ref]: e.png\n")
    assert links(doc) == ["b.md#real-heading", "b.md#nowhere", "c.md", "e.png"]
    assert anchors(tmp_path / "b.md") == {"real-heading"}


def readme_snippets() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


@pytest.mark.parametrize("index", range(len(readme_snippets())))
def test_readme_snippet_runs(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a snippet that writes files writes them here
    exec(compile(readme_snippets()[index], f"README.md python snippet {index}", "exec"), {"__name__": "__main__"})


def test_readme_has_snippets():
    assert len(readme_snippets()) >= 3  # the encoder in an env, the losses, the swapping buffer


def test_version_is_pyprojects_and_has_a_changelog_entry():
    import trakdis

    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert trakdis.__version__ == version  # installed from this tree (pip install -e .)
    assert f"## [{version}]" in (ROOT / "CHANGELOG.md").read_text()
