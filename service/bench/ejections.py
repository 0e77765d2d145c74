"""``meniscope bench ejections``: precision and recall of ejection detection (within +-2 frames) per kind of
window, live (the transient's look-ahead) and offline (more), the same detector.

Recordings of each kind alone and all kinds mixed (``meniscope simulate --kinds``), over seeds and noise
presets, rendered by our renderer into a scratch folder; or the recordings given (with their truth sidecars,
a Blender one for footage our renderer did not make). The recording's first ejection (frame 0, with no frames
before it to compare with) is not scored.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.verbs import add_scene_option

TOLERANCE = 2  # frames


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ejections", help="precision and recall of ejection detection per kind of window", description=__doc__
    )
    add_scene_option(p)
    p.add_argument(
        "--kinds",
        default="settled,heavy,light,4khz,drift,skip,faint,spatter,nominal,mixed",
        help="kinds to draw, each alone, 'mixed' for all in turn (default: all and mixed)",
    )
    p.add_argument("--seeds", default="0,1,2", help="seeds per kind and noise (default 0,1,2)")
    p.add_argument("--noise", default="lab,high", help="noise presets (default lab,high)")
    p.add_argument("--windows", type=int, default=20, help="windows per recording (default 20)")
    p.add_argument(
        "--recordings",
        type=Path,
        nargs="*",
        default=(),
        help="score these recordings (with REC.truth.json) instead of drawing new ones",
    )
    p.add_argument("--out", type=Path, required=True, help="EJECTIONS.json to write; a Markdown table beside it")
    p.set_defaults(func=run)


def score(found, true) -> tuple[int, int, int]:  # type: ignore[no-untyped-def]
    """(matched, found, true) within TOLERANCE frames, the recording's first true ejection (frame 0) and any found
    before the second's reach left out."""
    import numpy as np

    from service.validation.score import ejection_matches

    true = np.asarray(true, np.int64)[1:]
    found = np.asarray(found, np.int64)
    return ejection_matches(found[found >= true[0] - TOLERANCE] if true.size else found, true, TOLERANCE)


def measure(recording: Path) -> dict:
    """Detections of one recording by the detector with the live and the offline look-ahead, scored."""
    import json

    from service.pipeline.ejections import detect_ejections_streamed
    from service.pipeline.measures import recording_measures
    from service.simulate import truth_path

    truth = json.loads(truth_path(recording).read_text())
    fps = float(truth["recording"]["fps"])
    change, novelty = recording_measures(recording, fps)
    runs = {
        "live": detect_ejections_streamed(change, fps, offline=False, novelty=novelty),
        "offline": detect_ejections_streamed(change, fps, offline=True, novelty=novelty),
    }
    return {name: score(found, truth["ejections"]) for name, found in runs.items()}


def kind_of(recording: Path) -> str:
    """The row a given recording is scored in: its windows' kind (``simulate --kinds``), 'mixed' for several,
    else its file name."""
    import json

    from service.simulate import truth_path

    kinds = {w.get("kind") for w in json.loads(truth_path(recording).read_text()).get("windows", [])}
    return recording.name if kinds <= {None} else "mixed" if len(kinds) > 1 else str(kinds.pop())


def markdown(results: dict) -> str:
    """One row per kind: precision and recall of each detector, summed over seeds and noise levels."""
    names = ("live", "offline")
    lines = [
        "| kind | ejections | " + " | ".join(f"{n} P | {n} R" for n in names) + " |",
        "|---|---:|" + "---:|---:|" * len(names),
    ]
    for kind, rows in results["kinds"].items():
        cells = []
        for n in names:
            m, f, t = (sum(r[n][i] for r in rows) for i in range(3))
            cells += [f"{m / f:.3f}" if f else "-", f"{m / t:.3f}" if t else "-"]
        lines.append(f"| {kind} | {sum(r['live'][2] for r in rows)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + f"\n\nwithin +-{TOLERANCE} frames; {results['setup']}\n"


def run(args: argparse.Namespace) -> int:
    import tempfile

    from tqdm import tqdm

    from service.bench.results import write_results
    from service.camera_effects import noise_preset
    from service.scene import Scene
    from service.simulate import simulate
    from service.window_kinds import KINDS, kinds_named

    results: dict = {"kinds": {}}
    if args.recordings:
        for path in tqdm(args.recordings, desc="bench ejections", unit="recording"):
            results["kinds"].setdefault(kind_of(path), []).append({"recording": path.name, **measure(path)})
        results["setup"] = "recordings: " + ", ".join(p.name for p in args.recordings)
        write_results(args.out, results, markdown(results))
        return 0
    scene = Scene.load(args.scene)
    seeds = [int(s) for s in args.seeds.split(",")]
    noises = args.noise.split(",")
    kinds = args.kinds.split(",")
    jobs = [(k, s, n) for k in kinds for n in noises for s in seeds]
    with tempfile.TemporaryDirectory() as scratch:
        for kind, seed, noise in tqdm(jobs, desc="bench ejections", unit="recording"):
            names = ",".join(KINDS) if kind == "mixed" else kind
            out = Path(scratch) / f"{kind}-{noise}-{seed}.cine"
            simulate(
                scene,
                out,
                windows=args.windows,
                seed=seed,
                effects=noise_preset(noise, 12),
                noise=noise,
                kinds=kinds_named(names),
                kind_names=names.split(","),
            )
            results["kinds"].setdefault(kind, []).append({"seed": seed, "noise": noise, **measure(out)})
            out.unlink()
    results["setup"] = (
        f"our renderer, {args.windows} windows per recording, seeds {args.seeds}, noise {args.noise}, "
        f"scene {args.scene or 'default'}"
    )
    write_results(args.out, results, markdown(results))
    return 0
