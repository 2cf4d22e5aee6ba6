"""Hostile inputs, longer than the test suite runs them: outcomes by file kind and damage.

    python benchmarks/fuzz_inputs.py [--cases 2000] [--seed 0] [--out DIR]

The same seeds, damage (tests/fuzz_cases.py) and readers (tests/test_fuzz_inputs.py) as
the test suite, with ``--cases`` random cases per file kind (not the suite's fixed ones).
Each case ends ``accepted`` (the reader returned: the damage left a valid file, e.g. a
keyword amigo does not read), ``refused`` (InputError naming the file: the promise),
``not applicable`` (the damage does not apply to the seed), or ``BROKEN`` (any other
exception, a changed input, a partial output or more than 20 s: a bug; its case and error
are listed). Prints a table of counts by kind and damage, and the wall time; nothing is
asserted.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from hypothesis import HealthCheck, given, settings  # noqa: E402

import fuzz_cases  # noqa: E402
import test_fuzz_inputs as suite  # noqa: E402


def run(kind: str, seed: Path, work: Path, cases: int, counts, broken) -> None:
    strategy = fuzz_cases.npz_mutations() if kind == "model" else fuzz_cases.fits_mutations()

    @settings(
        max_examples=cases,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(mutation=strategy)
    def case(mutation: fuzz_cases.Mutation) -> None:
        try:
            result = suite.outcome(kind, seed, mutation, work)
        except Exception as error:  # a broken promise: recorded, not raised
            result = "BROKEN"
            broken.append((kind, mutation.describe(), f"{type(error).__name__}: {error}"[:200]))
        counts[(kind, mutation.kind)][result] += 1

    case()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=2000, help="cases per file kind")
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: temp)")
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="amigo-fuzz-"))
    seeds = suite.make_seeds(root / "seeds")
    counts: dict = collections.defaultdict(collections.Counter)
    broken: list = []
    start = time.perf_counter()
    for kind in suite.READERS:
        work = root / kind
        work.mkdir(parents=True, exist_ok=True)
        run(kind, seeds[kind], work, args.cases, counts, broken)
    seconds = time.perf_counter() - start
    outcomes = ("accepted", "refused", "not applicable", "BROKEN")
    print(f"| kind | damage | {' | '.join(outcomes)} |")
    print("|---|---|" + "---|" * len(outcomes))
    totals: collections.Counter[str] = collections.Counter()
    for (kind, damage), counter in sorted(counts.items()):
        totals.update(counter)
        print(f"| {kind} | {damage} | " + " | ".join(str(counter[o]) for o in outcomes) + " |")
    print("| all | all | " + " | ".join(str(totals[o]) for o in outcomes) + " |")
    print(f"\n| kind | {' | '.join(outcomes)} |")
    print("|---|" + "---|" * len(outcomes))
    by_kind: dict = collections.defaultdict(collections.Counter)
    for (kind, _), counter in counts.items():
        by_kind[kind].update(counter)
    for kind, counter in sorted(by_kind.items()):
        print(f"| {kind} | " + " | ".join(str(counter[o]) for o in outcomes) + " |")
    print(f"\n{sum(totals.values())} cases in {seconds:.0f} s")
    for kind, case, error in broken[:20]:
        print(f"BROKEN {kind} {case}: {error}")


if __name__ == "__main__":
    main()
