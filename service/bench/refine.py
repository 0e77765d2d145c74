"""``meniscope bench refine``: windows/s of ``meniscope analyze --refine`` (seconds per window) with its windows on
the local process pool and on local Dask clusters of 1, 2, ... worker processes, side by side on one recording,
and the CPU seconds each spent per window (this process and its workers: the figure a loaded machine leaves fair).

How a plant re-analyses an archive: the refinement of each window is an independent task, so windows/s should
grow with the workers until the cores run out; the REPORTs must be the same whichever ran them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.verbs import add_scene_option


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "refine", help="windows/s of analyze --refine: local pool against Dask workers", description=__doc__
    )
    p.add_argument("recording", type=Path, help="REC.cine or REC.avi, e.g. from `meniscope simulate --windows 10`")
    add_scene_option(p)
    p.add_argument("--dask-workers", default="1,2", help="sizes of the local Dask clusters (default 1,2)")
    p.add_argument("--out", type=Path, required=True, help="REFINE.json to write; a Markdown table beside it")
    p.set_defaults(func=run)


def measure(recording: Path, scene, opened, scheduler: str | None, workers: int | None) -> dict:  # type: ignore[no-untyped-def]
    """One refined analysis: wall seconds, windows refined per second, CPU seconds per window (this process and the
    workers: a local pool's processes, the cluster's at ``scheduler``), the load average at its end and the report's
    windows (to compare)."""
    import os
    import time

    from service import DEFAULT_MODELS
    from service.analysis.offline import analyse_recording

    cpu0, t0 = _cpu_s(scheduler), time.perf_counter()
    analysis = analyse_recording(
        recording,
        scene,
        "network",
        DEFAULT_MODELS,
        progress=False,
        opened=opened,
        refine=True,
        scheduler=scheduler,
        workers=workers,
    )
    seconds, cpu = time.perf_counter() - t0, _cpu_s(scheduler) - cpu0
    windows = analysis.report.windows
    return {
        "seconds": seconds,
        "windows": len(windows),
        "windows_per_s": len(windows) / seconds,
        "cpu_s_per_window": cpu / len(windows),
        "load": os.getloadavg()[0],
        "report": [w.model_dump(mode="json") for w in windows],
    }


def _cpu_s(scheduler: str | None) -> float:
    """CPU seconds (user and system) so far of this process and its workers: the children it has waited for (a
    local pool's processes, joined when the analysis ends) or, with ``scheduler``, the cluster's worker processes."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    total = own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime
    if scheduler is None:
        return total
    from distributed import Client

    with Client(scheduler, set_as_default=False) as client:
        return total + sum(client.run(_process_cpu_s).values())


def _process_cpu_s() -> float:
    """CPU seconds of the process it runs in, all its threads."""
    import time

    return time.process_time()


def _progress(run: dict) -> None:
    """One line as each run ends (a long benchmark that is cut short still says what it measured)."""
    print(
        f"bench refine: {run['name']}: {run['windows']} windows in {run['seconds']:.1f} s, "
        f"{run['cpu_s_per_window']:.1f} CPU s/window, load {run['load']:.1f}",
        flush=True,
    )


def differences(first: list[dict], other: list[dict]) -> list[str]:
    """Where ``other``'s windows differ from ``first``'s: one line per differing field (window index, field, both
    values), so that a report that is not the same says how."""
    if len(first) != len(other):
        return [f"{len(other)} windows against {len(first)}"]
    return [
        f"window {a['index']} {key}: {a.get(key)!r} against {b.get(key)!r}"
        for a, b in zip(first, other)
        for key in sorted(set(a) | set(b))
        if a.get(key) != b.get(key)
    ]


def markdown(results: dict) -> str:
    """One row per way of running."""
    lines = [
        "| windows run on | windows | seconds | windows/s | x local pool | CPU s/window | load (1 min) | same REPORT |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    base = results["runs"][0]["windows_per_s"]
    for r in results["runs"]:
        lines.append(
            f"| {r['name']} | {r['windows']} | {r['seconds']:.1f} | {r['windows_per_s']:.2f} | "
            f"{r['windows_per_s'] / base:.2f} | {r['cpu_s_per_window']:.1f} | {r['load']:.1f} | {'yes' if r['same_report'] else 'NO'} |"
        )
    notes = [f"- {r['name']}: {line}" for r in results["runs"] for line in r["differences"][:10]]
    text = "\n".join(lines) + f"\n\n{results['recording']}, {results['cores']} cores\n"
    return text + ("\nWhere the REPORTs differ (first 10 per run):\n\n" + "\n".join(notes) + "\n" if notes else "")


def run(args: argparse.Namespace) -> int:
    from service import DEFAULT_MODELS
    from service.bench.results import write_results
    from service.blas import usable_cores
    from service.errors import MeniscopeError
    from service.inverse.methods import open_method
    from service.scene import Scene

    try:
        sizes = [int(v) for v in args.dask_workers.split(",")]
    except ValueError:
        raise MeniscopeError("--dask-workers", f"expected counts like 1,2, got {args.dask_workers!r}") from None
    try:
        from distributed import LocalCluster
    except ImportError:
        raise MeniscopeError(
            "bench refine", "needs the Dask distributed package: pip install 'meniscope[scale]'"
        ) from None
    scene = Scene.load(args.scene)
    opened = open_method("network", scene, DEFAULT_MODELS)
    cores = usable_cores()
    print(f"bench refine: local pool of {cores} ...", flush=True)
    runs = [{"name": f"local pool, {cores} processes", **measure(args.recording, scene, opened, None, cores)}]
    _progress(runs[-1])
    for n in sizes:
        print(f"bench refine: Dask, {n} worker(s) ...", flush=True)
        with LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
        ) as cluster:
            runs.append(
                {
                    "name": f"Dask, {n} worker process(es)",
                    **measure(args.recording, scene, opened, cluster.scheduler_address, None),
                }
            )
        _progress(runs[-1])
    for r in runs:
        r["differences"] = differences(runs[0]["report"], r["report"])
        r["same_report"] = not r["differences"]
    for r in runs:
        del r["report"]
    results = {"recording": str(args.recording), "cores": cores, "runs": runs}
    write_results(args.out, results, markdown(results))
    return 0
