"""Building the C fuzz drivers under AddressSanitizer + UndefinedBehaviorSanitizer (shared by
the sanitizer tests): a missing compiler or a compiler without the sanitizers skips the test,
any other compile error fails it."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from spindle.native import build as native_build

SANITIZER_REPORT = re.compile(r"runtime error|AddressSanitizer|LeakSanitizer|SUMMARY:")
"""What a sanitizer prints when it finds something."""


def build(out: Path, sources: list[Path], variant: str, extra_flags: tuple[str, ...] = ()
          ) -> Path:
    """Compile ``sources`` into the executable ``out`` with the sanitizer flags of
    :func:`spindle.build.compile_flags` (``variant``: "double" or "float")."""
    try:
        compiler = native_build.compiler_command()
    except native_build.CBackendError as exc:
        pytest.skip(str(exc))
    flags = [f for f in native_build.compile_flags(variant, sanitize=True)
             if f not in ("-fPIC", "-shared")]
    cmd = [*compiler, *flags, *extra_flags, "-I", str(native_build.SOURCE_DIR), *map(str, sources),
           "-o", str(out), "-lm"]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0 and "sanitize" in result.stderr:
        pytest.skip(f"the compiler has no ASan/UBSan: {result.stderr.strip()[:200]}")
    assert result.returncode == 0, result.stderr
    return out
