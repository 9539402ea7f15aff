"""chain.c under AddressSanitizer + UndefinedBehaviorSanitizer, driven by random inputs.

spindle/native/c/fuzz/fuzz_chain.c pushes random, extreme and invalid samples through every entry
point of the chain (NaN/inf/huge times and values, time going backwards, corrupt clocks,
fractional and out-of-range counts, out-of-range lengths, NULL pointers, blocks of any size,
resets, the switch, corrupted configurations) and checks the header's contract itself: a
documented status, a failing push changes nothing, every output the chain holds is finite
with rates >= 0. The sanitizers abort on any memory error or undefined behaviour
(float-to-integer overflow included); zero reports are allowed.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from sanitized_build import SANITIZER_REPORT, build

from spindle.chain import ChainConfig
from spindle.chain.length_model import load_length_fits
from spindle.native import build as native_build

FUZZ_SOURCE = native_build.SOURCE_DIR / "fuzz" / "fuzz_chain.c"
STATUS = re.compile(r"(\d+):(\d+)")


def build_fuzzer(out: Path, variant: str) -> Path:
    return build(out, [*native_build.sources(), FUZZ_SOURCE], variant,
                 ("-fsanitize=float-cast-overflow",))


@pytest.fixture(scope="module")
def fuzzers(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    from spindle.native.chain import chain_config_struct

    root = tmp_path_factory.mktemp("fuzz_chain")
    fits = load_length_fits()
    out = {}
    for variant in native_build.VARIANTS:
        config = root / f"config_{variant}.bin"
        config.write_bytes(bytes(chain_config_struct(ChainConfig(), fits, variant)))
        out[variant] = (build_fuzzer(root / f"fuzz_chain_{variant}", variant), config)
    return out


def run_fuzzer(binary: Path, config: Path, seed: int, iterations: int) -> dict[int, int]:
    result = subprocess.run([str(binary), str(config), str(iterations), str(seed)],
                            capture_output=True, text=True, timeout=3000)
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-3000:]
    assert not SANITIZER_REPORT.search(report), report[-3000:]
    assert f"{iterations} iterations, 0 contract failures" in result.stdout, report[-3000:]
    statuses = {int(k): int(v) for k, v in STATUS.findall(
        result.stdout.split("statuses:")[1].split(",")[0])}
    accepted = int(re.search(r"accepted samples (\d+)", result.stdout).group(1))
    assert accepted > iterations // 5  # the chain really ran, not only refused
    assert int(re.search(r"restarts (\d+)", result.stdout).group(1)) > 0
    # every kind of outcome was reached: accepted pushes and each refusal of a bad input
    assert statuses[0] > iterations // 2
    for code in (2, 3, 9):  # non-finite, length range, config
        assert statuses[code] > 0, (code, result.stdout)
    # angles are clamped and long intervals restart: never refused (the driver checks it)
    assert statuses.get(10, 0) == statuses.get(12, 0) == 0
    return statuses


@pytest.mark.parametrize("variant", native_build.VARIANTS)
def test_chain_sanitizer_smoke(fuzzers, variant):
    run_fuzzer(*fuzzers[variant], seed=1, iterations=20_000)


@pytest.mark.slow
@pytest.mark.parametrize("variant", native_build.VARIANTS)
@pytest.mark.parametrize("seed", [2, 3, 4])
def test_chain_sanitizer_long_random_runs(fuzzers, variant, seed):
    run_fuzzer(*fuzzers[variant], seed=seed, iterations=1_000_000)
