"""Thousands of damaged inputs through every importer and the session loader (issue #19).

The long run of ``tests/test_fuzz_inputs.py``: the same damages and properties
(``tests/fuzz_inputs.py``), ``--examples`` per seed file and per session kind (default 1000).
Real vendor files come from ``../shared/realdata`` (or ``MOCAP_REALDATA``), read in place.
Prints, and writes to ``benchmarks/fuzz_inputs.json``, per target: examples run, how many
imported or loaded, how many got a clear error, and the first failure (a traceback or an error
that names no file) with the damage that caused it.

    python benchmarks/fuzz_inputs.py --examples 1000
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from fuzz_inputs import (  # noqa: E402
    REAL_IMPORTS,
    REALDATA,
    check_import,
    check_session,
    damaged,
    generated_imports,
    mutate_manifest,
)
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


def _run(name: str, examples: int, body) -> dict:
    counts: Counter = Counter()
    failure: dict = {}

    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(data=st.data())
    def prop(data):
        try:
            counts[body(data)] += 1
        except Exception as e:  # not BaseException: hypothesis steers itself with those
            counts["failure"] += 1
            failure.setdefault("error", f"{type(e).__name__}: {e}")
            failure.setdefault("traceback", traceback.format_exc(limit=6))
            raise

    t0 = time.perf_counter()
    try:
        prop()
    except BaseException:  # hypothesis re-raises the shrunk failure: recorded above
        pass
    out = {"target": name, "examples": sum(counts.values()), **dict(counts),
           "seconds": round(time.perf_counter() - t0, 1)}
    if failure:
        out["first_failure"] = failure
    print(json.dumps({k: v for k, v in out.items() if k != "first_failure"}), flush=True)
    if failure:
        print(failure["traceback"], flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=int, default=1000, help="examples per target (1000)")
    ap.add_argument("--out", type=Path, default=HERE / "fuzz_inputs.json")
    ap.add_argument("--only", default="",
                    help="run only targets whose name contains one of these (comma-separated)")
    args = ap.parse_args(argv)
    wanted = [w for w in args.only.split(",") if w] or [""]
    chosen = lambda target: any(w in target for w in wanted)  # noqa: E731
    from mocap.core.session import SessionWarning  # noqa: F401 - fail early if not installed

    import session_builders as sb

    results = []
    with tempfile.TemporaryDirectory(prefix="mocap-fuzz-") as tmp:
        tmp = Path(tmp)
        seeds = {k: p.read_bytes() for k, p in generated_imports(tmp / "seeds").items()}
        if REALDATA.is_dir():
            seeds |= {n: (REALDATA / n).read_bytes() for n in REAL_IMPORTS}
        for name, src in seeds.items():
            def body(data, name=name, src=src):
                _, bad = data.draw(damaged(src))
                path = tmp / "work" / name
                path.parent.mkdir(exist_ok=True)
                path.write_bytes(bad)
                return check_import(path, tmp / "work" / "session")
            if chosen(f"import {name}"):
                results.append(_run(f"import {name}", args.examples, body))
        kinds = {"2d_csv": lambda: sb.session_2d("csv"), "2d_mixed": lambda: sb.session_2d("mixed"),
                 "3d_csv": lambda: sb.session_3d("csv")}
        for kind, make in kinds.items():
            def body(data, make=make):
                import shutil

                root = tmp / "sess"
                if root.exists():
                    shutil.rmtree(root)
                make().write(root)
                files = sorted(p for p in root.rglob("*") if p.is_file())
                target = data.draw(st.sampled_from(files))
                _, bad = data.draw(damaged(target.read_bytes()))
                target.write_bytes(bad)
                return check_session(root)
            if chosen(f"load session {kind}"):
                results.append(_run(f"load session {kind}", args.examples, body))

            def body_manifest(data, make=make):
                import shutil

                root = tmp / "sess"
                if root.exists():
                    shutil.rmtree(root)
                spec = make()
                if not mutate_manifest(data.draw, spec.manifest):
                    return "skipped"
                spec.write(root)
                return check_session(root)
            if chosen(f"manifest values {kind}"):
                results.append(_run(f"manifest values {kind}", args.examples, body_manifest))
    total = sum(r["examples"] for r in results)
    failures = sum(r.get("failure", 0) for r in results)
    summary = {"examples": total, "failures": failures, "targets": results,
               "realdata": REALDATA.is_dir()}
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{total} examples over {len(results)} targets, {failures} failures; {args.out}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
