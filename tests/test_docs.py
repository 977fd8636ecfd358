"""Every ```python block of README.md and docs/*.md runs on its own: each in a fresh Python
process, in an empty folder, with nothing from the other blocks. A block preceded by the line
``<!-- full-test -->`` (a long run) belongs to the full tier (HEDGER_JAX_FULL_TESTS=1)."""
import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FULL_MARK = "<!-- full-test -->"
_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def blocks(path):
    """[(first line number, code, whether it is full-tier)] of a Markdown file."""
    text = open(path, encoding="utf-8").read()
    out = []
    for m in _BLOCK.finditer(text):
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        out.append((text.count("\n", 0, m.start()) + 2, m.group(1), before.strip() == FULL_MARK))
    return out


def _cases():
    files = ["README.md"] + sorted(os.path.join("docs", f) for f in
                                   os.listdir(os.path.join(ROOT, "docs")) if f.endswith(".md"))
    for rel in files:
        for line, code, full in blocks(os.path.join(ROOT, rel)):
            marks = [pytest.mark.full] if full else []
            yield pytest.param(code, id=f"{rel}:{line}", marks=marks)


def test_the_block_reader_finds_blocks_and_their_tier(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("text\n```python\nprint(1)\n```\n<!-- full-test -->\n```python\nx = 2\n```\n"
                  "```bash\nls\n```\n")
    assert blocks(str(md)) == [(3, "print(1)\n", False), (7, "x = 2\n", True)]
    assert len(list(_cases())) >= 5         # README.md and docs/ have blocks to run


@pytest.mark.parametrize("code", list(_cases()))
def test_code_block_runs_on_its_own(code, tmp_path):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
               MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
