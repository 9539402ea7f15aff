"""The C sizes and offsets of proprio.h's structs, printed by a compiled probe (for the
tests that compare the ctypes mirrors with the header)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from spindle.native import build


def c_layout(checks: list[tuple[str, str]], tmp_path: Path,
             flags: tuple[str, ...] = ()) -> list[tuple[int, int]]:
    """(sizeof(struct), offsetof(struct, field)) for each (struct, field) of ``checks``."""
    lines = "".join(f'printf("%lu %lu\\n", (unsigned long)sizeof({c}), '
                    f"(unsigned long)offsetof({c}, {f}));\n" for c, f in checks)
    src = tmp_path / "layout.c"
    src.write_text('#include <stdio.h>\n#include <stddef.h>\n#include "proprio.h"\n'
                   f"int main(void) {{\n{lines}return 0;\n}}\n")
    exe = tmp_path / "layout"
    subprocess.run([*build.compiler_command(), *build.WARNING_FLAGS, *flags, "-I",
                    str(build.SOURCE_DIR), str(src), "-o", str(exe)], check=True)
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    return [(int(out[2 * k]), int(out[2 * k + 1])) for k in range(len(checks))]
