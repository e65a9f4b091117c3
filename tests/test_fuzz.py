# SPDX-License-Identifier: BSD-3-Clause
"""A short run of the fuzzer (scripts/fuzz.py): hostile files through `run` and `eval`.

Every case runs in a forked child under a 3 GB memory limit and a timeout; the contract
allows only exit 0, or exit 2 with one line on stderr (and no output file left behind).
The long run (>= 2000 cases) is documented in docs/results.md.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

from tests.helpers import script_module

CASES = 200  # split over PARTS tests so pytest-xdist runs them side by side
PARTS = 4


def _fuzz_module() -> ModuleType:
    return script_module("fuzz")


@pytest.fixture(scope="module")
def fuzz() -> ModuleType:
    return _fuzz_module()


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory, fuzz: ModuleType) -> tuple[Path, object]:
    work = tmp_path_factory.mktemp("fuzz")
    fuzz.preimport()
    return work, fuzz.Bases(work, scale=0.6)


def _describe(outcomes: list) -> str:
    return "\n".join(f"{o.case.family}/{o.case.name}: {o.kind} rc={o.rc} "
                     f"{' '.join(o.case.argv)}\n{o.stderr[-600:]}" for o in outcomes)


@pytest.mark.parametrize("part", range(PARTS))
def test_short_fuzz_run_breaks_no_contract(part: int, fuzz: ModuleType,
                                           work: tuple[Path, object]) -> None:
    """test that a seeded short fuzz run (all families) has no traceback, memory blow-up,
    hang, multi-line error, partial file or accepted bad input"""
    root, bases = work
    mine = fuzz.make_cases(CASES, 7, list(fuzz.FAMILIES), bases, root / f"p{part}",
                           part=(part, PARTS))
    outcomes = [fuzz.run_case(c, timeout=60.0, mem_bytes=3 * fuzz.GIB) for c in mine]
    breaks = [o for o in outcomes if o.kind in fuzz.BREAKS]
    assert not breaks, _describe(breaks)
    assert sum(o.kind == "ok" for o in outcomes) >= len(outcomes) // 5  # not all refused


@pytest.mark.parametrize("kind", ["zstd-bomb-4g", "zstd-bomb-trunc", "zstd-declared-small",
                                  "huge-chunk-size", "huge-record-len"])
def test_resource_attacks_stay_small(kind: str, fuzz: ModuleType,
                                     work: tuple[Path, object]) -> None:
    """test that decompression bombs and huge declared sizes are skipped with the log read
    (exit 0) within a few hundred MB more than the process had"""
    import random

    root, bases = work
    case_dir = root / "res" / kind
    case_dir.mkdir(parents=True)
    case = fuzz.gen_resource(0, random.Random(kind), bases, case_dir, kind=kind)
    out = fuzz.run_case(case, timeout=60.0, mem_bytes=3 * fuzz.GIB)
    assert out.kind in ("ok", "clean"), _describe([out])
    import resource
    parent_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    assert out.maxrss_mb < parent_mb + 400, (out.maxrss_mb, parent_mb)


def test_totals_table_counts_by_family_and_outcome(fuzz: ModuleType) -> None:
    """test that the totals table has a row per family, the totals and the breaks"""
    cases = [fuzz.Case("bytes", "a", []), fuzz.Case("bytes", "b", []),
             fuzz.Case("eval", "c", [])]
    outs = [fuzz.Outcome(cases[0], "ok", 0, "", 0.1, 1.0),
            fuzz.Outcome(cases[1], "traceback", 1, "", 0.1, 1.0),
            fuzz.Outcome(cases[2], "clean", 2, "x", 0.1, 1.0)]
    table = fuzz.totals_table(outs)
    assert "| bytes | 2 | 1 | 0 | 1 | 1 |" in table
    assert "| eval | 1 | 0 | 1 | 0 | 0 |" in table
    assert "| **all** | 3 | 1 | 1 | 1 | 1 |" in table
