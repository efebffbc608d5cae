"""The repository stands alone: no file refers to a path outside it, and every relative
link of README.md and docs/ points at a file of the repository."""

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).parents[1]
#: References that only make sense on the machine the project was written on: the sibling
#: folder of contracts and data, the workspace's absolute paths, the thesis's text file and
#: the old name of docs/design.md.
OUTSIDE = re.compile(r"\.\./shared|/work/|thesis\.txt|DESIGN\.md")
SKIP_DIRS = {".git", ".venv", "data", "build", "dist", ".prefect", "__pycache__",
             ".hypothesis", ".pytest_cache"}
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _files() -> list[Path]:
    """The tracked files (a git checkout), else every file under the root but the
    virtual environment and outputs (an unpacked sdist)."""
    try:
        names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                               check=True).stdout.decode().split("\0")
        return [ROOT / n for n in names if n and (ROOT / n).is_file()]
    except (OSError, subprocess.CalledProcessError):
        return [p for p in ROOT.rglob("*") if p.is_file()
                and not SKIP_DIRS & set(p.relative_to(ROOT).parts)]


def test_no_file_refers_outside_the_repository():
    me = Path(__file__).resolve()
    bad = []
    for path in _files():
        if path.resolve() == me:
            continue
        try:
            text = path.read_text()
        except (UnicodeDecodeError, OSError):
            continue  # binary: images, captures, parquet
        for n, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not bad, "references outside the repository:\n" + "\n".join(bad)


def test_readme_and_docs_links_stay_inside():
    bad = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in LINK.findall(page.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor of the same page
            path = (page.parent / target.split("#")[0]).resolve()
            if ROOT.resolve() not in path.parents or not path.exists():
                bad.append(f"{page.relative_to(ROOT)}: {target}")
    assert not bad, "links outside the repository or to missing files:\n" + "\n".join(bad)
