"""docs/layout.md names only paths that exist: every backticked file or folder in its tables is
found relative to the row's folder (a first cell such as `train/vae_gan/`), the table's (the line
"In `src/`, ..." above it) or the repository's root. `simd/{conv,dense}.rs` names each file.

    python -m pytest tests/test_layout.py      # the standard library and pytest
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PATH = re.compile(r"^[\w./{},-]+(\.(rs|py|md|sh|toml|txt|html|json|pyi)|/)$")


def expand(token):
    """`a/{b,c}.rs` as `a/b.rs`, `a/c.rs`."""
    match = re.search(r"\{([^}]*)\}", token)
    if not match:
        return [token]
    return [x for part in match.group(1).split(",") for x in expand(token[:match.start()] + part + token[match.end():])]


def named_paths(text):
    """(line number, the folders a token may be relative to, token) for every path in the tables."""
    section, found = "", []
    for number, line in enumerate(text.splitlines(), 1):
        heading = re.match(r"^In `([^`]+/)`", line)
        if heading:
            section = heading.group(1)
        if not line.startswith("|") or line.startswith("| ---"):
            continue
        cells = line.strip("|").split("|")
        first = re.fullmatch(r"\s*`([^`]+/)`(\s*\(.*\))?\s*", cells[0])
        row = section + first.group(1) if first else section
        for token in re.findall(r"`([^`]+)`", line):
            token = token.split("::")[0]
            if PATH.match(token):
                found.append((number, (row, section, ""), token))
    return found


def missing(text):
    out = []
    for number, bases, token in named_paths(text):
        for path in expand(token):
            if not any((ROOT / base / path).exists() for base in bases):
                out.append(f"line {number}: {path} (from {bases[0] or 'the root'})")
    return out


def test_every_path_docs_layout_names_exists():
    text = (ROOT / "docs" / "layout.md").read_text()
    assert len(named_paths(text)) > 100, "the tables were not read"
    assert missing(text) == []


def test_a_path_that_does_not_exist_is_found():
    text = "In `src/`, one file:\n\n| file | what |\n| --- | --- |\n| `config.rs`, `policy.rs` | x |\n" \
           "| `train/` | `heads.rs`, `policy.rs`, `simd/{conv,nothing}.rs` |\n"
    assert missing(text) == ["line 5: policy.rs (from src/)", "line 6: policy.rs (from src/train/)",
                             "line 6: simd/conv.rs (from src/train/)", "line 6: simd/nothing.rs (from src/train/)"]



LINK = re.compile(r"\]\(([^)\s]+)\)")


def broken_links(page):
    """`line: link` for each relative link of a markdown file whose file or folder does not
    exist (anchors and web addresses are not followed)."""
    out = []
    for number, line in enumerate(page.read_text().splitlines(), 1):
        for link in LINK.findall(line):
            if re.match(r"^[a-z]+:", link) or link.startswith("#"):
                continue
            if not (page.parent / link.partition("#")[0]).exists():
                out.append(f"{number}: {link}")
    return out


def repository_pages(root):
    """The markdown files of the repository under ``root``: not those of build outputs or of
    hidden folders (``.git``, a virtualenv such as ``weights/.venv`` and the packages in it)."""
    return [p for p in root.rglob("*.md")
            if not any(part in {"target", "node_modules"} or part.startswith(".") for part in p.relative_to(root).parts[:-1])]


def test_markdown_links_lead_somewhere():
    pages = repository_pages(ROOT)
    assert len(pages) > 10
    broken = [f"{p.relative_to(ROOT)}:{b}" for p in pages for b in broken_links(p)]
    assert broken == [], broken


def test_pages_of_a_virtualenv_are_not_the_repository_s(tmp_path):
    for page in ("README.md", "docs/a.md", "weights/.venv/lib/pkg/Privacy.md", "target/doc/b.md"):
        (tmp_path / page).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / page).write_text("x\n")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in repository_pages(tmp_path)) == ["README.md", "docs/a.md"]


def test_a_broken_link_is_found(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("[here](page.md) [web](https://x.org) [top](#top)\n[gone](history/gone.md#a)\n")
    assert broken_links(page) == ["2: history/gone.md#a"]
