"""Every ```python block of the README runs as written: in order, in one fresh interpreter
started from the repository root, each block in a namespace of its own (so each must stand
alone, as a reader would paste it)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)

RUNNER = """
import json, sys, traceback
for index, code in enumerate(json.load(sys.stdin)):
    try:
        exec(compile(code, f"README python block {index}", "exec"), {"__name__": "__main__"})
    except BaseException:
        traceback.print_exc()
        sys.exit(f"README python block {index} failed:\\n{code}")
    print(f"block {index} ok", flush=True)
"""


def python_blocks() -> list[str]:
    return BLOCK.findall(README.read_text(encoding="utf-8"))


def test_every_readme_python_block_runs():
    blocks = python_blocks()
    assert len(blocks) >= 4  # chain, spindle, env, rendering
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")  # the rendering example, headless
    run = subprocess.run([sys.executable, "-c", RUNNER], input=json.dumps(blocks), cwd=ROOT,
                         capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    done = [line for line in run.stdout.splitlines() if re.fullmatch(r"block \d+ ok", line)]
    assert done == [f"block {i} ok" for i in range(len(blocks))]
