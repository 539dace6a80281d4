"""The corrupted-bag fuzz test (``test/test_bag_fuzz.py``, issue #25) with a larger budget.

``make test`` runs a few seeded examples per property; this runs ``--examples`` per property (default
200, a few seconds each), still derandomized, and writes ``bench/fuzz.json``: the examples, the
outcome of each property and the wall time. A failure prints hypothesis' minimal falsifying plan.

    PYTHONPATH=. .venv/bin/python bench/bench_fuzz.py [--examples 200] [--out bench/fuzz.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=200, help="examples per property (default 200)")
    parser.add_argument("--out", type=Path, default=BENCH / "fuzz.json")
    args = parser.parse_args()
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(REPO), "PTM_FUZZ_EXAMPLES": str(args.examples)}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rA", "test/test_bag_fuzz.py"]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    print(proc.stdout[-20000:], proc.stderr[-4000:], sep="\n")
    outcomes = {}
    for line in proc.stdout.splitlines():
        word, _, test = line.partition(" ")
        if word in ("PASSED", "FAILED", "ERROR") and "::" in test:
            outcomes[test.split("::")[1].split(" ")[0]] = word.lower()
    result = {
        "examples_per_property": args.examples,
        "outcomes": outcomes,
        "exit_code": proc.returncode,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
