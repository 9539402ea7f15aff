"""spindle.c under AddressSanitizer + UndefinedBehaviorSanitizer, driven by random inputs.

spindle/native/c/fuzz/fuzz_spindle.c draws states, constants and inputs (NaN, inf, huge, negative
drive, out-of-range lengths, h <= 0, theta outside [0, 1], NULL pointers, random state bytes)
and checks the header's promises itself: a status of enum ps_status, the documented status for
each invalid input, the state and outputs untouched on failure, finite rates >= 0 on success.
The sanitizers abort on any memory error or undefined behaviour; zero reports are allowed.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from sanitized_build import SANITIZER_REPORT, build

from spindle.native import build as native_build

FUZZ_SOURCE = native_build.SOURCE_DIR / "fuzz" / "fuzz_spindle.c"


# the embedded options too (the levers of spindle.native.m0plus.measure): no libm cube root,
# fixed iterations
BUILDS = {"double": ("double", ()), "float": ("float", ()),
          "float-embedded": ("float", ("-DPS_FAST_CBRT", "-DPS_CBRT_REFINE=0",
                                       "-DPS_NEWTON_ITER=2"))}


@pytest.fixture(scope="module")
def fuzzers(tmp_path_factory) -> dict[str, Path]:
    if not FUZZ_SOURCE.exists():  # an installed wheel ships the library sources only
        pytest.skip(f"{FUZZ_SOURCE} not found (run the tests from a source checkout)")
    root = tmp_path_factory.mktemp("fuzz")
    library = [p for p in native_build.sources() if p.name == "spindle.c"]
    return {name: build(root / f"fuzz_spindle_{name}", [*library, FUZZ_SOURCE], variant, defs)
            for name, (variant, defs) in BUILDS.items()}


def run_fuzzer(binary: Path, seed: int, iterations: int) -> dict[str, int]:
    result = subprocess.run([str(binary), str(seed), str(iterations)], capture_output=True,
                            text=True, timeout=600)
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-3000:]
    assert not SANITIZER_REPORT.search(report), report[-3000:]
    counts = dict(re.findall(r"(\w+)=(\d+)", result.stdout))
    counts = {k: int(v) for k, v in counts.items()}
    assert counts["iterations"] == iterations
    # both paths exercised: accepted steps and refused ones
    assert counts["ok"] > iterations // 10 and counts["refused"] > iterations // 10
    return counts


@pytest.mark.parametrize("variant", list(BUILDS))
def test_sanitizer_smoke(fuzzers, variant):
    run_fuzzer(fuzzers[variant], seed=1, iterations=20_000)


@pytest.mark.slow
@pytest.mark.parametrize("variant", list(BUILDS))
@pytest.mark.parametrize("seed", [2, 3, 4, 5])
def test_sanitizer_long_random_runs(fuzzers, variant, seed):
    run_fuzzer(fuzzers[variant], seed=seed, iterations=1_000_000)


def test_the_sanitizers_do_report(tmp_path):
    """The build really is instrumented: an out-of-bounds read and a signed overflow abort."""
    src = tmp_path / "bad.c"
    src.write_text(
        "#include <stdlib.h>\n"
        "int main(int argc, char **argv) {\n"
        "    int a[3] = {1, 2, 3}; int big = 2147483647;\n"
        "    (void)argv;\n"
        "    if (argc > 2) return big + argc;\n"
        "    return a[argc + 2];\n"
        "}\n")
    binary = build(tmp_path / "bad", [src], "double")
    for args in ([], ["x", "y"]):
        result = subprocess.run([str(binary), *args], capture_output=True, text=True)
        assert result.returncode != 0
        assert SANITIZER_REPORT.search(result.stderr), result.stderr
