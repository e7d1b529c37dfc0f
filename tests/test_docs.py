"""README.md and docs/*.md: relative links resolve, anchors name headings, CI runs the README test.

Anchors follow GitHub's heading slugs: lowercase, punctuation other than ``-`` and ``_``
dropped, each space a ``-``, repeated headings suffixed ``-1``, ``-2``, ...
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
INLINE_CODE = re.compile(r"`[^`]*`")


def documentation_files(root: Path = ROOT) -> list[Path]:
    """README.md and every docs/*.md under ``root``."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def prose_lines(text: str) -> list[str]:
    """Lines outside fenced code blocks, inline code removed."""
    lines, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(INLINE_CODE.sub("", line))
    return lines


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading's text."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file (repeated slugs get -1, -2, ...)."""
    seen: dict[str, int] = {}
    found = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        match = re.match(r"#{1,6} +(.*?) *#* *$", line)
        if fenced or not match:
            continue
        slug = github_slug(match.group(1).replace("`", ""))
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def broken_links(path: Path) -> list[str]:
    """Relative links of ``path`` whose file is missing or whose #anchor names no heading."""
    problems = []
    for line in prose_lines(path.read_text(encoding="utf-8")):
        for target in LINK.findall(line):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            linked = (path.parent / file_part).resolve() if file_part else path
            if not linked.exists():
                problems.append(f"{path.name}: {target}: no file {linked}")
            elif anchor and (linked.suffix != ".md" or anchor not in anchors(linked)):
                problems.append(f"{path.name}: {target}: no heading #{anchor} in {linked.name}")
    return problems


def readme_test_command(readme: Path) -> str:
    """The command of the README's fenced block that runs pytest."""
    blocks = re.findall(r"```bash\n(.*?)```", readme.read_text(encoding="utf-8"), flags=re.S)
    commands = [line for block in blocks for line in block.splitlines() if "pytest" in line]
    assert len(commands) == 1, commands
    return commands[0]


def test_every_relative_link_and_anchor_resolves():
    files = documentation_files()
    assert len(files) > 2, files
    problems = [problem for path in files for problem in broken_links(path)]
    assert problems == []


def test_every_docs_page_is_linked_from_the_readme():
    readme_targets = {
        target.partition("#")[0]
        for line in prose_lines((ROOT / "README.md").read_text(encoding="utf-8"))
        for target in LINK.findall(line)
    }
    pages = {f"docs/{path.name}" for path in (ROOT / "docs").glob("*.md")}
    assert pages - readme_targets == set()


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = [line for line in (ROOT / ".ci/run").read_text().splitlines() if line.strip()]
    assert ci_lines[-1] == readme_test_command(ROOT / "README.md")


def test_checker_flags_missing_files_and_anchors(tmp_path):
    (tmp_path / "docs").mkdir()
    page = "# A page\n\n## Faulty input, divergence and Ctrl-C\n"
    (tmp_path / "docs" / "page.md").write_text(page)
    (tmp_path / "README.md").write_text(
        "# Title\n\n"
        "[ok](docs/page.md#faulty-input-divergence-and-ctrl-c) [ok](#title)\n"
        "[bad anchor](docs/page.md#faulty-input) [bad file](docs/gone.md)\n"
        "`[code](docs/gone.md)`\n\n```\n[fenced](docs/gone.md)\n```\n"
    )
    problems = broken_links(tmp_path / "README.md")
    assert len(problems) == 2, problems
    assert "#faulty-input" in problems[0] and "gone.md" in problems[1]


def test_github_slug_rules():
    assert github_slug("Status (issue 3: LM back end)") == "status-issue-3-lm-back-end"
    assert github_slug("B = 32 aggregate throughput") == "b--32-aggregate-throughput"
    assert github_slug("2D LiDAR: scan matching") == "2d-lidar-scan-matching"
