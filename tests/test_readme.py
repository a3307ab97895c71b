"""The README as a test: every shell and Python block of README.md and of the quick starts in
docs/ runs as written, in order, in one scratch folder (issue 15).

* ```sh / ```bash blocks run in bash with ``set -e``; ``octofactor`` and ``python`` are this
  interpreter (``python -m pipelines``) with this checkout first on the path.
* ```python blocks run in a fresh interpreter in the same folder.
* The folder has ``../shared`` -> the shared data, as beside a clone; blocks that use
  ``../shared`` are skipped when it is missing.
* A block right after ``<!-- not run: REASON -->`` is skipped (it needs something the test
  must not do, e.g. ``pip install``); every other block runs. Blocks without a language
  (usage synopses, output) are text.
"""
from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# the README first, then the quick starts of docs/ (their blocks use the README's outputs)
DOCUMENTS = ("README.md", "docs/octree.md", "docs/vanishing_points.md", "docs/evaluation.md",
             "docs/plugins.md", "docs/registration.md")
LANGUAGES = {"sh": "sh", "bash": "sh", "python": "python"}
FENCE = re.compile(r"^```(\w*)\s*$")
NOT_RUN = re.compile(r"<!--\s*not run:\s*(.+?)\s*-->")


def extract_blocks(path: Path) -> list[dict]:
    """Fenced blocks of ``path``: language, text, first line number, skip reason."""
    blocks, current, skip = [], None, None
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fence = FENCE.match(line)
        if current is None:
            marker = NOT_RUN.search(line)
            if marker:
                skip = marker.group(1)
            elif fence:
                current = {"language": fence.group(1), "lines": [], "line": number + 1,
                           "skip": skip, "document": path.relative_to(REPO).as_posix()}
                skip = None
            elif line.strip():
                skip = None
        elif fence and not fence.group(1):
            current["text"] = "\n".join(current.pop("lines")) + "\n"
            blocks.append(current)
            current = None
        else:
            current["lines"].append(line)
    return blocks


BLOCKS = [b for doc in DOCUMENTS for b in extract_blocks(REPO / doc)
          if b["language"] in LANGUAGES]


def _shared_dir() -> Path | None:
    for candidate in (REPO.parent / "shared", Path("/work/shared")):
        if (candidate / "data").is_dir():
            return candidate
    return None


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """``<tmp>/repo`` with ``../shared`` and a bin/ of ``octofactor`` and ``python``."""
    root = tmp_path_factory.mktemp("readme")
    work = root / "repo"
    work.mkdir()
    shared = _shared_dir()
    if shared is not None:
        (root / "shared").symlink_to(shared)
    bin_dir = root / "bin"
    bin_dir.mkdir()
    for name, command in (("octofactor", f'exec "{sys.executable}" -m pipelines "$@"'),
                          ("python", f'exec "{sys.executable}" "$@"')):
        script = bin_dir / name
        script.write_text(f"#!/bin/sh\n{command}\n")
        script.chmod(script.stat().st_mode | stat.S_IXUSR)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               MPLBACKEND="Agg", TQDM_DISABLE="1")
    return work, env, shared is not None


def test_every_block_is_found():
    counts = {doc: sum(b["document"] == doc for b in BLOCKS) for doc in DOCUMENTS}
    assert counts["README.md"] >= 6, counts
    assert all(counts[doc] >= 1 for doc in DOCUMENTS), counts
    skipped = [b for b in BLOCKS if b["skip"]]
    # only `make demo`/`make test` (this test runs inside make test) and `pip install`
    assert len(skipped) <= 2, [(b["document"], b["line"]) for b in skipped]


@pytest.mark.parametrize("block", BLOCKS, ids=[f"{b['document']}:{b['line']}" for b in BLOCKS])
def test_block_runs_as_written(block, workdir):
    work, env, have_shared = workdir
    if block["skip"]:
        pytest.skip(block["skip"])
    if "../shared" in block["text"] and not have_shared:
        pytest.skip("needs the shared data beside the repository")
    if LANGUAGES[block["language"]] == "sh":
        command = ["bash", "-e", "-o", "pipefail", "-c", block["text"]]
    else:
        command = [sys.executable, "-c", block["text"]]
    result = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, (
        f"{block['document']}:{block['line']} failed ({result.returncode}):\n"
        f"{block['text']}\n--- stdout\n{result.stdout[-3000:]}\n--- stderr\n"
        f"{result.stderr[-3000:]}")
    # a normal run prints no third-party warnings (issue 15)
    assert "Warning" not in result.stderr, result.stderr[-3000:]
