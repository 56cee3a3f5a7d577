"""Many sessions at once on Dask (dask.distributed).

A lab runs many sessions (robots, skin revisions, days). ``run_batch`` submits one
``mocap run`` per session to a Dask cluster: a ``LocalCluster`` of single-threaded worker
processes by default (each session then reconstructs its takes in one process: the cluster
spreads sessions over the cores), or an existing scheduler by address. A session that fails is
reported with its error and does not stop the others. Results go to ``ROOT/<session name>/`` and
a summary to ``ROOT/batch.json``.
"""

from __future__ import annotations

import json
import time
import traceback
from pathlib import Path
from typing import Callable

from mocap.core.atomic import write_text


def _run_one(session_dir: str, out_dir: str, writers=None) -> dict:
    """Worker side: one session, the pipeline's summary or the error (never raises).
    ``writers``: the run's ``mocap.workflows.run.result.RunWriters`` (None: data files only)."""
    import dataclasses

    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.result import RunWriters
    from mocap.workflows.run.settings import RunSettings

    t0 = time.perf_counter()
    try:
        res = run_session(session_dir, out_dir, settings=dataclasses.replace(RunSettings(), jobs=1),
                          writers=writers if writers is not None else RunWriters())
        return {"session": session_dir, "out": out_dir, "ok": True,
                "seconds": round(time.perf_counter() - t0, 2), "stages": res.summary["stages"],
                "audit": res.summary["audit"]["verdict"]}
    except Exception as e:  # reported, not raised: one bad session must not stop the batch
        return {"session": session_dir, "out": out_dir, "ok": False,
                "seconds": round(time.perf_counter() - t0, 2),
                "error": f"{type(e).__name__}: {e}",
                "traceback": traceback.format_exc(limit=3)}


def _out_names(sessions: list[Path]) -> list[str]:
    names, seen = [], {}
    for s in sessions:
        base = s.name if s.name != "session" else s.parent.name
        k = seen.get(base, 0)
        seen[base] = k + 1
        names.append(base if k == 0 else f"{base}_{k + 1}")
    return names


def run_batch(sessions, root, *, scheduler: str | None = None, workers: int | None = None,
              progress: Callable[[str], None] | None = None, writers=None) -> dict:
    """Run every session; return (and write to ROOT/batch.json) the per-session outcomes.

    writers : each run's figure and recording writers (``mocap.workflows.run.result.RunWriters``; ``mocap
        batch`` passes ``mocap.outputs.run_writers.WRITERS``, whose module-level functions pickle by
        reference to the workers); None: data files only.
    """
    from dask.distributed import Client, LocalCluster, as_completed

    say = progress or (lambda m: None)
    sessions = [Path(s) for s in sessions]
    root = Path(root)
    outs = [root / n for n in _out_names(sessions)]
    cluster = None
    if scheduler:
        client = Client(scheduler)
    else:
        import os

        n = workers or min(len(sessions), os.cpu_count() or 1)
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    t0 = time.perf_counter()
    try:
        futures = [client.submit(_run_one, str(s), str(o), writers, pure=False)
                   for s, o in zip(sessions, outs)]
        results = []
        for i, fut in enumerate(as_completed(futures), start=1):
            r = fut.result()
            results.append(r)
            say(f"[{i}/{len(futures)}] {r['session']}: "
                + ("ok" if r["ok"] else f"FAILED ({r['error']})"))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    order = {str(s): i for i, s in enumerate(sessions)}
    results.sort(key=lambda r: order[r["session"]])
    summary = {"sessions": results, "ok": sum(r["ok"] for r in results),
               "failed": sum(not r["ok"] for r in results),
               "seconds": round(time.perf_counter() - t0, 2),
               "scheduler": scheduler or "LocalCluster"}
    write_text(root / "batch.json", json.dumps(summary, indent=2))
    return summary
