"""A sampled mutation score (``make mutate-sample``; not part of CI).

A full mutmut run of ``kernel.py`` (about 2,400 mutants) takes hours on two cores, so this scores a seeded
random sample of each module's mutants instead, in the scratch copies of ``tools/mutate.py``
(``build/mutmut/<module>/``, each module judged by its own tests):

1. mutmut generates every mutant and collects which tests call which function (``mutmut run`` with a
   name that matches no mutant: generation and the test-to-function map happen before the name filter,
   which then stops the run);
2. ``mutmut results --all true`` lists every mutant name; ``--sample N --seed S`` draws N of them
   (``random.Random(S).sample`` over the sorted names: the same N, seed and code give the same mutants);
3. ``mutmut run NAME ...`` runs only those (each against the tests that call the mutated function);
4. the verdicts are tallied: killed, timeout, survived, no tests (no test calls the mutated function),
   other (suspicious, segfault, not checked, ...).

The score counts only the mutants that reach a test: ``(killed + timeout) / reached`` with
``reached = killed + timeout + survived + suspicious`` (a suspicious verdict counts as not killed);
mutants that no test reaches are reported apart. The 95 % interval is Wilson's. The summary is printed
and written to ``build/mutmut/<module>/sample_summary.txt`` (and ``sample_summary.json``, with the
survivors' names; ``mutmut show NAME`` inside that folder prints a survivor's diff).

    python tools/mutation_sample.py ps_optim --sample 100 --seed 1
    python tools/mutation_sample.py kernel --sample 300 --seed 1 --max-children 2
    python tools/mutation_sample.py ps_optim --sample 100 --seed 1 --retest   # after adding tests

A mutant already judged keeps its verdict (mutmut's cache) unless ``--retest`` names the sample's
non-killed mutants again; ``--retest`` also drops mutmut's test-to-function map, which it would otherwise
keep for every test it has seen, changed or not.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Dict, Iterable, List, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mutate import MODULES, prepare, results  # noqa: E402

_NO_SUCH_MUTANT = "torch_hsh_mutation_sample_lists_only__no_such_mutant"
DETECTED = ("killed", "timeout")
NOT_DETECTED = ("survived", "suspicious")


def wilson(k: int, n: int, z: float = 1.959963984540054) -> Tuple[float, float]:
    """Wilson score interval for k successes out of n (95 % by default); (nan, nan) for n = 0."""
    if n <= 0:
        return (float("nan"), float("nan"))
    if not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    p = k / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return (max(0.0, centre - half), min(1.0, centre + half))


def sample_names(names: Iterable[str], n: int, seed: int) -> List[str]:
    """A seeded sample of n names (all of them when n >= their number), in sorted order; independent of
    the order the names come in."""
    pool = sorted(set(names))
    if n >= len(pool):
        return pool
    return sorted(random.Random(seed).sample(pool, n))


def tally(status_by_name: Dict[str, str]) -> Dict[str, object]:
    """Counts of the verdicts of the sampled mutants, the score over those that reach a test and its
    Wilson 95 % interval."""
    c = Counter(status_by_name.values())
    killed, timeout = c.get("killed", 0), c.get("timeout", 0)
    survived, suspicious = c.get("survived", 0), c.get("suspicious", 0)
    no_tests = c.get("no tests", 0)
    other = sum(v for k, v in c.items() if k not in DETECTED + NOT_DETECTED + ("no tests",))
    reached = killed + timeout + survived + suspicious
    lo, hi = wilson(killed + timeout, reached)
    return {
        "sampled": len(status_by_name), "reached": reached, "killed": killed, "timeout": timeout,
        "survived": survived, "suspicious": suspicious, "no_tests": no_tests, "other": other,
        "score": (killed + timeout) / reached if reached else float("nan"), "wilson95": [lo, hi],
        "survivors": sorted(k for k, v in status_by_name.items() if v in NOT_DETECTED),
    }


def format_summary(module: str, t: Dict[str, object], command: str) -> str:
    lo, hi = t["wilson95"]
    return (
        f"{module}: sampled {t['sampled']}, reached a test {t['reached']} "
        f"(killed {t['killed']}, timeout {t['timeout']}, survived {t['survived']}, suspicious {t['suspicious']}); "
        f"no tests {t['no_tests']}, other {t['other']}; "
        f"score {100 * t['score']:.1f} %, Wilson 95 % [{100 * lo:.1f}, {100 * hi:.1f}] %\n"
        f"  {t['mutants_total']} mutants in all; ran {t['ran']} of the sample in {t['run_seconds']} s "
        f"({t['seconds']} s with the generation and the clean test runs)\n"
        f"  command: {command}\n"
    )


def _mutmut(work: Path, *args: str, capture: bool = False) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "mutmut", *args], cwd=work, env=env,
                          capture_output=capture, text=True)


def generate(work: Path, max_children: int) -> Dict[str, str]:
    """Generate the mutants and the test map (a run that matches no mutant), then list every mutant."""
    r = _mutmut(work, "run", "--max-children", str(max_children), _NO_SUCH_MUTANT, capture=True)
    found = results(work)
    # the expected stop is the name filter's; a failing stats run (a test that fails under mutmut) stops earlier
    if not found or "nothing matches" not in r.stdout + r.stderr:
        sys.stderr.write(r.stdout[-4000:] + r.stderr[-4000:])
        raise SystemExit(f"mutmut stopped before the mutants were listed in {work} (its output above)")
    return found


def run_module(name: str, n: int, seed: int, max_children: int, retest: bool, command: str) -> Dict[str, object]:
    work = prepare(name)
    if retest:  # mutmut re-maps only new tests to the functions they call: a changed test keeps its old map
        (work / "mutants" / "mutmut-stats.json").unlink(missing_ok=True)
    t0 = time.perf_counter()
    before = generate(work, max_children)
    chosen = sample_names(before, n, seed)
    todo: Sequence[str] = [m for m in chosen if before[m] == "not checked"
                           or (retest and before[m] not in DETECTED + ("no tests",))]
    print(f"{name}: {len(before)} mutants, sample of {len(chosen)} (seed {seed}); running {len(todo)}", flush=True)
    t1 = time.perf_counter()
    for i in range(0, len(todo), 200):  # keep the command line short
        rc = _mutmut(work, "run", "--max-children", str(max_children), *todo[i:i + 200]).returncode
        if rc:
            print(f"{name}: mutmut run returned {rc} (its output above)", file=sys.stderr, flush=True)
    after = results(work)
    t = tally({m: after.get(m, "not checked") for m in chosen})
    t.update(module=name, mutants_total=len(before), seed=seed, command=command, ran=len(todo),
             seconds=round(time.perf_counter() - t0), run_seconds=round(time.perf_counter() - t1))
    text = format_summary(name, t, command)
    print(text, flush=True)
    (work / "sample_summary.txt").write_text(text + "  survivors: " + " ".join(t["survivors"]) + "\n")
    (work / "sample_summary.json").write_text(json.dumps(t, indent=1) + "\n")
    return t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("modules", nargs="*", help=f"which modules: {', '.join(MODULES)} (default: all)")
    ap.add_argument("--sample", type=int, default=100, help="mutants drawn per module (default 100)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the draw (default 1)")
    ap.add_argument("--max-children", type=int, default=os.cpu_count() or 1, help="parallel mutant workers")
    ap.add_argument("--retest", action="store_true", help="run the sample's survivors again (after new tests)")
    args = ap.parse_args(argv)
    bad = [m for m in args.modules if m not in MODULES]
    if bad:
        ap.error(f"unknown module(s) {', '.join(bad)}; choose from {', '.join(MODULES)}")
    for name in args.modules or list(MODULES):
        command = f"python tools/mutation_sample.py {name} --sample {args.sample} --seed {args.seed}"
        run_module(name, args.sample, args.seed, args.max_children, args.retest, command)
    return 0


if __name__ == "__main__":
    sys.exit(main())
