"""``meniscope validate``: the paper's validation figures (PNGs and figures.json) for a model folder and databases."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.verbs import add_scene_option


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "validate",
        help="score every inverse method on simulated recordings and draw the validation figures",
        description="Run the networks of MODEL_DIR and, per render database, the exact, approximate and "
        "regularised nearest-neighbour methods on simulated recordings (with REC.truth.json) that no model saw; "
        "write per-frame scores, search costs, recall@10 and window-fit errors to OUT/figures.json, and PNGs: "
        "inferred against true D(0, t) per method, lab frames beside their VAE reconstructions and beside renders "
        "of the coefficients inferred from them.",
    )
    add_scene_option(p)
    p.add_argument("--models", type=Path, required=True, help="model folder (`meniscope train`; e.g. models/default)")
    p.add_argument(
        "--database",
        type=Path,
        action="append",
        default=[],
        help="render database folder (`meniscope database`); repeat to compare, e.g. 20k and 100k",
    )
    p.add_argument(
        "--recording",
        type=Path,
        action="append",
        default=[],
        required=True,
        help="simulated recording with its .truth.json; repeat for several",
    )
    p.add_argument(
        "--lab-video", type=Path, help="recording whose frames the image figures show (default: the first --recording)"
    )
    p.add_argument("--out", type=Path, required=True, help="folder for figures.json and the PNGs")
    p.add_argument(
        "--record",
        action="store_true",
        help="also add the networks' scores to MODEL_DIR/manifest.json (its file hashes are kept)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.scene import Scene
    from service.validation.report import validate  # onnxruntime and the renderer load only when the verb runs

    document = validate(
        Scene.load(args.scene),
        args.models,
        args.database,
        args.recording,
        args.out,
        lab_video=args.lab_video,
        record=args.record,
    )
    for name, rec in document["recordings"].items():
        print(f"{name} ({rec['renderer']}, {rec['frames_scored']} frames scored):")
        for method, m in rec["methods"].items():
            r = "n/a" if m["centre_correlation"] is None else f"{m['centre_correlation']:.3f}"
            rmse = ", ".join(f"{k} {v:.3g}" for k, v in m["rmse"].items())
            o = m["oscillation"]
            ro = "n/a" if o["correlation"] is None else f"{o['correlation']:.3f}"
            print(
                f"  {method:24s} RMSE {rmse}; D(0, t) r {r}; within windows: RMSE {o['rmse']:.3g}, r {ro}; "
                f"{m['seconds_per_frame'] * 1e3:.3g} ms/frame"
            )
    print(f"{args.out / 'figures.json'}: written with {len(document['figures'])} figures")
    return 0
