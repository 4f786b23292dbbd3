"""Run every benchmark (or those named) and print their figures:

    .venv/bin/python -m tests.benchmarks                 # all
    .venv/bin/python -m tests.benchmarks extract_ct      # one: tests/benchmarks/bench_extract_ct.py
"""

import importlib
import pkgutil
import sys
from pathlib import Path


def main() -> None:
    available = sorted(m.name.removeprefix("bench_") for m in pkgutil.iter_modules(
        [str(Path(__file__).parent)]) if m.name.startswith("bench_"))
    chosen = sys.argv[1:] or available
    unknown = sorted(set(chosen) - set(available))
    if unknown:
        sys.exit(f"unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(available)}")
    for name in chosen:
        print(f"\n=== {name} ===", flush=True)
        module = importlib.import_module(f"tests.benchmarks.bench_{name}")
        module.main([]) if module.main.__code__.co_argcount else module.main()


if __name__ == "__main__":
    main()
